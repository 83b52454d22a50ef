"""Every renderer backend against the pure-torch reference: images and gradients of all parameters.

Tolerances (stated once, used below):
- cpu vs torch: both float32 with the same operation order, so images agree to rounding: ``atol=2e-5, rtol=1e-4``
  (colour and alpha in [0, 1], depth in metres). Gradients are sums over hundreds of pixels in a different order:
  ``rtol=2e-3`` and ``atol = 2e-4 * max|reference gradient|`` per parameter tensor.
- gsplat vs torch: in ``test_gsplat.py`` (a CPU stand-in built from gsplat's own rules, and CUDA where there is one).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render import get_renderer
from eligsir_o3d.render.cpu_backend import CpuRenderer

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def look_at_pose(eye, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose of an OpenCV camera (z forward, y down) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def edge_case_scene(n: int = 400, seed: int = 0, max_opacity: float = 0.99):
    """Random Gaussians around the origin plus the hard cases, seen by a camera at z = -3 looking at the origin.

    Hard cases: behind the camera and inside the near plane, centres off-screen with their tails on it, very small
    (1e-4 m, the 0.3 px^2 low-pass dominates) and very large (2 m, covering the whole image), nearly transparent
    (opacity around the 1/255 skip threshold), needles (300:1, where float32 rounding of sigma is worst), and a stack of opaque Gaussians in front of everything so that
    compositing stops early (transmittance below 1e-4).
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.8, 0.6, 0.6])
    scales = torch.exp(torch.empty(n, 3).uniform_(-4.0, -1.5, generator=g))
    opac = torch.empty(n).uniform_(0.05, max_opacity, generator=g)
    m = n // 10
    means[:m, 2] = -3.0 - torch.rand(m, generator=g)  # behind the camera
    means[m:2 * m, 2] = -3.0 + 0.005  # inside the near plane
    means[2 * m:3 * m, :2] = torch.tensor([1.6, 1.2]) * torch.sign(torch.randn(m, 2, generator=g))  # off-screen
    scales[2 * m:3 * m] = 0.3
    scales[3 * m:4 * m] = 1e-4  # sub-pixel
    scales[4 * m:4 * m + 3] = 2.0  # huge
    opac[4 * m:4 * m + 3] = torch.minimum(torch.tensor(0.3), opac[4 * m:4 * m + 3])
    opac[5 * m:6 * m] = torch.empty(m).uniform_(0.002, 0.006, generator=g)  # around alpha 1/255
    scales[7 * m:8 * m] = torch.tensor([0.6, 0.002, 0.002])  # needles, in random orientations
    # opaque stack right in front of the image centre: transmittance falls below 1e-4 there
    means[6 * m:6 * m + 12] = torch.tensor([0.0, 0.0, -1.5]) + 0.05 * torch.randn(12, 3, generator=g)
    scales[6 * m:6 * m + 12] = 0.15
    opac[6 * m:6 * m + 12] = max_opacity
    quats = torch.randn(n, 4, generator=g)
    colors = torch.rand(n, 3, generator=g)
    params = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors)
    return params, look_at_pose([0.0, 0.0, -3.0])


def render_with_grads(renderer, params, camera, T, background, seed: int = 1):
    """Render, back-propagate a fixed random weighting of colour, depth and alpha; return outputs and gradients."""
    ps = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = renderer.render(ps["means"], ps["quats"], ps["scales"], ps["opacities"], ps["colors"], camera, T,
                          background=background)
    g = torch.Generator().manual_seed(seed)
    h, w = camera.height, camera.width
    wc, wd, wa = torch.rand(h, w, 3, generator=g), torch.rand(h, w, generator=g), torch.rand(h, w, generator=g)
    loss = (out.color * wc.to(out.color)).sum() + (out.depth * wd.to(out.depth)).sum() + \
        (out.alpha * wa.to(out.alpha)).sum()
    loss.backward()
    return out, {k: v.grad for k, v in ps.items()}


def assert_grads_close(got, ref, rtol, atol_frac):
    for k in PARAMS:
        scale = float(ref[k].abs().max())
        torch.testing.assert_close(got[k], ref[k], rtol=rtol, atol=atol_frac * max(scale, 1e-12),
                                   msg=lambda m, k=k: f"gradient of {k}: {m}")


CAMERAS = [Camera(64, 48, 60.0, 60.0, 31.5, 23.5), Camera(70, 45, 55.0, 58.0, 30.0, 25.0)]


def _blocks():
    from eligsir_o3d.render._cpu_kernels import BLOCKS
    return sorted(BLOCKS)


@pytest.mark.parametrize("block", _blocks(), ids=lambda b: f"block{b}")
@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: f"{c.width}x{c.height}")
@pytest.mark.parametrize("seed", [0, 1])
def test_cpu_matches_reference(camera, seed, block):
    """Every block shape the kernels can be built with (a compile-time parameter, so all run on any CPU)."""
    params, T = edge_case_scene(seed=seed)
    bg = torch.tensor([0.2, 0.4, 0.6])
    ref_out, ref_g = render_with_grads(get_renderer("torch"), params, camera, T, bg)
    out, g = render_with_grads(CpuRenderer(block=block), params, camera, T, bg)
    # the scene really exercises early termination (alpha stops just short of 1 - 1e-4) and partial coverage
    a = ref_out.alpha.detach()
    assert 0.999 < float(a.max()) <= 1.0 - 1e-4 + 1e-6 and float(a.min()) < 0.5
    for name in ("color", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, name), getattr(ref_out, name), atol=2e-5, rtol=1e-4,
                                   msg=lambda m, name=name: f"{name}: {m}")
    assert torch.equal(out.radii, ref_out.radii)
    assert_grads_close(g, ref_g, rtol=2e-3, atol_frac=2e-4)
    for k in PARAMS:
        assert torch.isfinite(g[k]).all(), k
    # culled Gaussians (behind the camera, off-screen) get exactly zero gradient, as in the reference
    culled = ref_out.radii == 0
    assert culled.any()
    assert float(g["means"][culled].abs().max()) == 0.0


@pytest.mark.parametrize("seed", [0, 4])
def test_cpu_binning_equals_reference_binning(seed):
    """The compiled tile binning gives the reference's per-tile lists, in the same front-to-back order."""
    from eligsir_o3d.render.cpu_backend import bin_tiles_csr, tile_lists
    from eligsir_o3d.render.projection import bin_tiles, project
    params, T = edge_case_scene(n=600, seed=seed)
    params["means"][::7, 2] = params["means"][::7, 2].round(decimals=1)  # ties in depth: broken by index
    camera = CAMERAS[1]
    proj = project(params["means"], params["quats"], params["scales"], camera, T)
    bins = bin_tiles(proj, camera.width, camera.height)
    offsets, flat, tiles_x = bin_tiles_csr(proj, camera.width, camera.height)
    ref_offsets, ref_flat = tile_lists(bins)
    assert tiles_x == bins.tiles_x
    assert torch.equal(offsets, ref_offsets) and torch.equal(flat, ref_flat)
    # the binning kernel in parallel parts (a map with many Gaussians in view): the same lists for any part count
    from eligsir_o3d.render._cpu_binning import bin_tiles_fill
    radii = proj.radii.to(torch.int32).numpy()
    vis = np.flatnonzero(radii > 0)
    by_depth = vis[np.argsort(proj.depths.numpy()[vis], kind="stable")].astype(np.int64)
    args = (proj.means2d.float().numpy(), radii, by_depth, tiles_x, bins.tiles_y)
    for chunks in (1, 2, 5, 64):
        o, f = bin_tiles_fill(*args, chunks)
        assert np.array_equal(o, ref_offsets.numpy()) and np.array_equal(f, ref_flat.numpy()), chunks


@pytest.mark.parametrize("seed", [0, 7])
def test_cpu_projection_matches_reference_projection(seed):
    """The compiled projection against the torch one: values, radii and gradients of a loss on all three outputs,
    including Gaussians behind the camera, at the near plane and far off-screen (where the Jacobian is clamped)."""
    from eligsir_o3d.render.cpu_backend import project_cpu
    from eligsir_o3d.render.projection import project
    params, T = edge_case_scene(n=600, seed=seed)
    params["means"][-40:, :2] *= 6.0  # far outside the frustum: the x/z, y/z clamp is active
    params["quats"][-1] = 0.0  # a degenerate quaternion
    camera = CAMERAS[seed % 2]
    g = torch.Generator().manual_seed(seed + 10)
    w2, w3, w1 = torch.randn(600, 2, generator=g), torch.randn(600, 3, generator=g), torch.randn(600, generator=g)
    outs, grads = [], []
    for fn in (project, project_cpu):
        ps = {k: params[k].clone().requires_grad_(True) for k in ("means", "quats", "scales")}
        proj = fn(ps["means"], ps["quats"], ps["scales"], camera, T)
        ((proj.means2d * w2).sum() + (proj.conics * w3).sum() + (proj.depths * w1).sum()).backward()
        outs.append(proj)
        grads.append(ps)
    ref, got = outs
    torch.testing.assert_close(got.means2d, ref.means2d, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(got.conics, ref.conics, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(got.depths, ref.depths, atol=1e-6, rtol=1e-6)
    assert float((got.radii != ref.radii).float().mean()) <= 0.005  # 3 sqrt(lambda) within rounding of an integer
    assert bool(((got.radii - ref.radii).abs() <= 1).all())
    for k in ("means", "quats", "scales"):
        r, c = grads[0][k].grad, grads[1][k].grad
        finite = torch.isfinite(r).all(-1)  # the degenerate quaternion's gradient is huge (1 / 1e-12) in both
        torch.testing.assert_close(c[finite], r[finite], rtol=1e-3, atol=1e-4 * float(r[finite].abs().max()),
                                   msg=lambda m, k=k: f"gradient of {k}: {m}")


def test_cpu_early_termination_and_skip_match_reference():
    """A stack of opaque Gaussians (stops after two) plus a veil just below and above alpha 1/255."""
    camera = Camera(32, 32, 40.0, 40.0, 15.5, 15.5)
    n = 8
    means = torch.zeros(n, 3)
    means[:, 2] = torch.linspace(1.0, 2.0, n)
    params = dict(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), scales=torch.full((n, 3), 0.5),
                  opacities=torch.tensor([0.0039, 0.0040, 0.99, 0.99, 0.99, 0.99, 0.5, 0.5]),
                  colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(3)))
    ref_out, ref_g = render_with_grads(get_renderer("torch"), params, camera, np.eye(4), None)
    out, g = render_with_grads(get_renderer("cpu"), params, camera, np.eye(4), None)
    torch.testing.assert_close(out.color, ref_out.color, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(out.alpha, ref_out.alpha, atol=2e-5, rtol=1e-4)
    assert_grads_close(g, ref_g, rtol=2e-3, atol_frac=2e-4)
    # at the centre the opaque pair ends compositing: the Gaussians behind it change nothing there
    front = {k: v[:6] for k, v in params.items()}
    out_front = get_renderer("cpu").render(**front, camera=camera, T_world_cam=np.eye(4))
    assert torch.equal(out_front.color[16, 16], out.color[16, 16].detach())
    assert float(out.alpha[16, 16]) > 0.999


def test_cpu_float64_inputs_and_unused_outputs():
    """float64 parameters are rendered in float32 and get float64 gradients; a loss on colour only works."""
    params, T = edge_case_scene(n=120, seed=5)
    camera = CAMERAS[0]
    ps = {k: v.double().requires_grad_(True) for k, v in params.items()}
    out = CpuRenderer().render(ps["means"], ps["quats"], ps["scales"], ps["opacities"], ps["colors"], camera, T)
    assert out.color.dtype == torch.float64
    out.color.sum().backward()
    assert all(ps[k].grad is not None and ps[k].grad.dtype == torch.float64 for k in PARAMS)


def test_cpu_renders_empty_and_fully_culled_scenes():
    camera = CAMERAS[1]
    empty = dict(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 3),
                 opacities=torch.zeros(0), colors=torch.zeros(0, 3))
    out = CpuRenderer().render(**empty, camera=camera, T_world_cam=np.eye(4), background=torch.ones(3))
    assert out.color.shape == (45, 70, 3) and torch.all(out.color == 1.0) and torch.all(out.alpha == 0)
    behind = dict(means=torch.tensor([[0.0, 0.0, -1.0]]), quats=torch.tensor([[1.0, 0, 0, 0]]),
                  scales=torch.full((1, 3), 0.1), opacities=torch.tensor([0.9]), colors=torch.ones(1, 3),
                  )
    ps = {k: v.clone().requires_grad_(True) for k, v in behind.items()}
    out = CpuRenderer().render(**ps, camera=camera, T_world_cam=np.eye(4))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0) and int(out.radii[0]) == 0
    out.color.sum().backward()
    assert float(ps["means"].grad.abs().sum()) == 0.0


def test_cpu_rejects_bad_shapes_with_a_clear_error():
    params, T = edge_case_scene(n=120)
    params["opacities"] = params["opacities"][:, None]  # [N, 1] instead of [N]
    with pytest.raises(ValueError, match="opacities must be"):
        CpuRenderer().render(**params, camera=CAMERAS[0], T_world_cam=T)


@pytest.mark.skipif(__import__("platform").machine().lower() not in ("x86_64", "amd64"),
                    reason="haswell is an x86-64 CPU; on this machine the kernels compile for its own ISA only")
def test_cpu_kernels_for_avx2_match_reference():
    """The kernels compiled for an AVX2 CPU (haswell: no AVX-512, whatever this machine has) against the reference,
    in a fresh process, since numba's target is fixed per process."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    code = ("import sys; sys.path[:0] = ['tests/render', 'tests/core']; import test_render_agreement as t; "
            "import test_fmath as f; "
            "from eligsir_o3d.render._cpu_kernels import target_features, default_block; "
            "name, feats = target_features(); assert name == 'haswell' and '+avx512f' not in feats, (name, feats); "
            "[t.test_cpu_matches_reference(t.CAMERAS[1], 0, b) for b in t._blocks()]; "
            "t.test_cpu_early_termination_and_skip_match_reference(); f.test_exp_neg_is_within_two_ulp_of_exp(); "
            "f.test_exp32_is_within_two_ulp_of_exp_and_clamps(); f.test_a_vectorised_loop_gives_the_scalar_bits(); "
            "print('haswell ok', default_block())")
    env = dict(os.environ, NUMBA_CPU_NAME="haswell", NUMBA_CPU_FEATURES="", PYTHONPATH=str(root))
    res = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True)
    assert res.returncode == 0 and "haswell ok" in res.stdout, res.stderr[-3000:]


def test_cpu_kernels_are_loaded_lazily():
    """``import eligsir_o3d.render`` must not import numba or compile anything."""
    import subprocess
    import sys
    code = ("import sys, eligsir_o3d.render as r; "
            "assert 'eligsir_o3d.render._cpu_kernels' not in sys.modules; assert 'numba' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
