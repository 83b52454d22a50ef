"""The torch reference renderer (gradients against finite differences, shapes, edge behaviour) and SH colour."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render import available_backends, get_renderer
from eligsir_o3d.render.sh import C0, C1, rgb_to_sh0, sh0_to_rgb, sh_bases, sh_eval, view_dirs

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def tiny_scene(n: int = 6, seed: int = 0, dtype=torch.float64):
    """A few soft, semi-transparent Gaussians well inside a 24x20 image, 2-3 m in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.empty(n, 2).uniform_(-0.5, 0.5, generator=g),
                       torch.empty(n, 1).uniform_(2.0, 3.0, generator=g)], 1)
    return dict(
        means=means.to(dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=torch.empty(n, 3, dtype=dtype).uniform_(0.08, 0.2, generator=g),
        opacities=torch.empty(n, dtype=dtype).uniform_(0.2, 0.7, generator=g),
        colors=torch.rand(n, 3, generator=g, dtype=dtype),
    )


CAM = Camera(24, 20, 20.0, 21.0, 11.5, 9.5)


def test_reference_gradients_match_finite_differences():
    """float64 gradcheck of a scalar loss on colour + depth + alpha w.r.t. all five parameter tensors.

    The compositing has thresholds (alpha < 1/255 skipped, transmittance cut-off, tile culling); the scene and the
    seed keep every pixel away from them, so the loss is smooth within the finite-difference step.
    """
    params = tiny_scene()
    g = torch.Generator().manual_seed(1)
    wc = torch.rand(CAM.height, CAM.width, 3, generator=g, dtype=torch.float64)
    wd = torch.rand(CAM.height, CAM.width, generator=g, dtype=torch.float64)
    wa = torch.rand(CAM.height, CAM.width, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float64)
    T = np.eye(4)
    T[:3, 3] = [0.05, -0.03, 0.1]
    renderer = get_renderer("torch")

    def loss(means, quats, scales, opacities, colors):
        out = renderer.render(means, quats, scales, opacities, colors, CAM, T, background=bg)
        return (out.color * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()

    inputs = tuple(params[k].clone().requires_grad_(True) for k in PARAMS)
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_reference_output_shapes_and_ranges():
    params = {k: v.float() for k, v in tiny_scene(n=20, seed=2).items()}
    cam = Camera(37, 29, 30.0, 30.0, 18.0, 14.0)  # not a multiple of the 16 px tile
    out = get_renderer("torch").render(**params, camera=cam, T_world_cam=np.eye(4), background=torch.ones(3))
    assert out.color.shape == (29, 37, 3) and out.depth.shape == (29, 37) and out.alpha.shape == (29, 37)
    assert out.radii.shape == (20,) and out.radii.dtype == torch.int32 and out.means2d.shape == (20, 2)
    assert out.visible.dtype == torch.bool and bool(out.visible.all())
    assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) < 1.0
    assert float(out.color.min()) >= 0.0 and float(out.color.max()) <= 1.0 + 1e-6
    covered = out.alpha > 0.5
    assert covered.any()
    # expected depth lies within the Gaussians' depth range wherever they cover the pixel
    assert float(out.depth[covered].min()) >= 2.0 - 1e-4 and float(out.depth[covered].max()) <= 3.0 + 1e-4


def test_single_gaussian_colour_depth_and_centre():
    """One opaque isotropic Gaussian on the optical axis: its colour and depth at the centre pixel."""
    cam = Camera(33, 33, 40.0, 40.0, 16.0, 16.0)
    params = dict(means=torch.tensor([[0.0, 0.0, 2.0]]), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                  scales=torch.full((1, 3), 0.2), opacities=torch.tensor([0.999]),
                  colors=torch.tensor([[0.9, 0.2, 0.1]]))
    for name in available_backends("cpu"):
        out = get_renderer(name).render(**params, camera=cam, T_world_cam=np.eye(4), background=torch.zeros(3))
        torch.testing.assert_close(out.color[16, 16], torch.tensor([0.9, 0.2, 0.1]) * 0.999, atol=1e-5, rtol=0)
        assert abs(float(out.depth[16, 16]) - 2.0) < 1e-5
        torch.testing.assert_close(out.means2d[0], torch.tensor([16.0, 16.0]))
        # symmetric around the centre pixel (integer pixel centres)
        torch.testing.assert_close(out.alpha[16, 10], out.alpha[16, 22])
        torch.testing.assert_close(out.alpha[10, 16], out.alpha[22, 16])


def test_gaussians_behind_camera_or_off_screen_are_culled():
    cam = Camera(32, 24, 30.0, 30.0, 15.5, 11.5)
    params = dict(means=torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, 0.005], [50.0, 0.0, 2.0]]),
                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(3, 1), scales=torch.full((3, 3), 0.1),
                  opacities=torch.full((3,), 0.9), colors=torch.ones(3, 3))
    out = get_renderer("torch").render(**params, camera=cam, T_world_cam=np.eye(4), background=torch.tensor([0.1, 0.2, 0.3]))
    assert out.radii.tolist() == [0, 0, 0]
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    torch.testing.assert_close(out.color, torch.tensor([0.1, 0.2, 0.3]).expand(24, 32, 3))


def test_renderer_dispatch_and_errors():
    assert get_renderer("torch").name == "torch"
    assert "torch" in available_backends("cpu")
    if "cpu" in available_backends("cpu"):
        assert get_renderer("auto", "cpu").name == "cpu"
    with pytest.raises(ValueError, match="unknown renderer"):
        get_renderer("opengl")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            get_renderer("gsplat", "cpu")


# ---------------------------------------------------------------- spherical harmonics ---------------------------------

def test_sh_degree0_round_trip_and_clamp():
    rgb = torch.rand(10, 3)
    sh = rgb_to_sh0(rgb)[:, None, :]  # [N, 1, 3]
    torch.testing.assert_close(sh_eval(sh, torch.randn(10, 3)), rgb)
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
    dark = torch.full((2, 1, 3), -5.0)
    assert torch.all(sh_eval(dark, torch.randn(2, 3)) == 0.0)


def test_sh_bases_known_values_and_norm_independence():
    z = torch.tensor([[0.0, 0.0, 1.0]])
    b = sh_bases(1, z)[0]
    torch.testing.assert_close(b, torch.tensor([C0, 0.0, C1, 0.0]))
    y = torch.tensor([[0.0, 1.0, 0.0]])
    torch.testing.assert_close(sh_bases(1, y)[0], torch.tensor([C0, -C1, 0.0, 0.0]))  # 3DGS sign: -C1 * y
    sh = torch.randn(5, 16, 3)
    d = torch.randn(5, 3)
    torch.testing.assert_close(sh_eval(sh, d), sh_eval(sh, 7.5 * d))
    # fewer bands than stored: the extra coefficients are ignored
    torch.testing.assert_close(sh_eval(sh, d, degree=1), sh_eval(sh[:, :4], d))


@pytest.mark.parametrize("k", [4, 9])
def test_compiled_degree1_sh_is_the_torch_formula_values_and_gradients(k):
    """The float32 CPU path of degree 1 (compiled, :mod:`eligsir_o3d.render._sh_kernels`) against the torch
    formulation in float64: colours, the clamp, and the gradients of the coefficients and the directions."""
    g = torch.Generator().manual_seed(3)
    sh = torch.randn(300, k, 3, generator=g) * 0.8
    sh[:40, 0] = -10.0  # clamped to black: no gradient there
    dirs = torch.randn(300, 3, generator=g) * 2.0
    w = torch.randn(300, 3, generator=g)
    outs = []
    for dt in (torch.float32, torch.float64):  # float64 takes the torch formula
        s, d = sh.to(dt).detach().clone().requires_grad_(True), dirs.to(dt).detach().clone().requires_grad_(True)
        c = sh_eval(s, d, degree=1)
        (c * w.to(dt)).sum().backward()
        outs.append((c.detach().double(), s.grad.double(), d.grad.double()))
    (c32, gs32, gd32), (c64, gs64, gd64) = outs
    torch.testing.assert_close(c32, c64, rtol=1e-5, atol=1e-6)
    assert torch.all(c32[:40] == 0.0) and torch.all(gs32[:40] == 0.0)
    torch.testing.assert_close(gs32, gs64, rtol=1e-5, atol=1e-6)
    assert torch.all(gs32[:, 4:] == 0.0)  # the bands above degree 1 are not used
    torch.testing.assert_close(gd32, gd64, rtol=1e-4, atol=1e-6)


def test_sh_bases_are_orthonormal():
    """Monte-Carlo check: the 16 real SH bases are orthonormal on the sphere (4 pi E[b_i b_j] = delta_ij)."""
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(400_000, 3, generator=g, dtype=torch.float64), dim=-1)
    b = sh_bases(3, d)
    gram = 4 * math.pi * (b.T @ b) / d.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.02, rtol=0)


def test_sh_matches_gsplat_torch_implementation():
    impl = pytest.importorskip("gsplat.cuda._torch_impl")
    g = torch.Generator().manual_seed(4)
    for degree in range(4):
        sh = torch.randn(40, 16, 3, generator=g, dtype=torch.float64)
        dirs = torch.randn(40, 3, generator=g, dtype=torch.float64)
        ref = torch.clamp_min(impl._spherical_harmonics(degree, dirs, sh) + 0.5, 0.0)
        torch.testing.assert_close(sh_eval(sh, dirs, degree), ref)


def test_sh_gradients_and_view_dirs():
    sh = torch.randn(7, 9, 3, dtype=torch.float64, requires_grad=True)
    means = torch.randn(7, 3, dtype=torch.float64, requires_grad=True)
    T = np.eye(4)
    T[:3, 3] = [0.5, -0.2, -3.0]
    assert torch.autograd.gradcheck(lambda s, m: sh_eval(s, view_dirs(m, T)), (sh, means))
    torch.testing.assert_close(view_dirs(means, T), means - torch.tensor([0.5, -0.2, -3.0], dtype=torch.float64))


def test_sh_rejects_bad_shapes():
    with pytest.raises(ValueError):
        sh_eval(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError):
        sh_eval(torch.zeros(4, 4, 3), torch.zeros(5, 3))
    with pytest.raises(ValueError):
        sh_eval(torch.zeros(4, 4, 3), torch.zeros(4, 3), degree=2)


def test_a_deferred_output_makes_means2d_when_it_is_read_first():
    """``means2d`` read before ``radii`` comes from the screen function, not the RenderOutput class default."""
    from eligsir_o3d.render.base import DeferredRenderOutput

    calls = []

    def screen():
        calls.append(1)
        return torch.tensor([3, 0], dtype=torch.int32), torch.tensor([[1.0, 2.0], [float("nan")] * 2])

    raw = (torch.zeros(2, 2, 4), torch.zeros(2, 2), None)
    out = DeferredRenderOutput(torch.zeros(2, 2), None, None, raw, screen=screen)
    assert out.means2d.shape == (2, 2) and out.means2d[0, 1] == 2.0
    assert out.radii.tolist() == [3, 0] and len(calls) == 1
    eager = DeferredRenderOutput(torch.zeros(2, 2), torch.ones(1, dtype=torch.int32), torch.ones(1, 2), raw)
    assert eager.means2d.shape == (1, 2)
