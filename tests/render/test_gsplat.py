"""The gsplat backend against gsplat's own conventions, on the same scenes in two ways:

- ``standin-cpu`` (default suite): gsplat's real ``rasterization`` with its five CUDA ops replaced by the stand-in of
  ``gsplat_standin.py``, built from gsplat's pure-torch twins and its kernels' rules - so the backend's conversions
  (world-to-camera ``viewmats``, +0.5 principal point, SH pass-through, RGB+D, radii, means2d) meet gsplat's
  conventions, not the project's own projection;
- ``cuda`` (skipped without a GPU): gsplat's kernels.

Tolerances against the torch reference, on scenes whose opacities stay below 0.35 (there gsplat's opacity-aware
boxes and the reference's 3-sigma circles admit the same Gaussians to every pixel that matters):
- stand-in: float32 with the same formulas in another order: images ``atol=2e-5, rtol=1e-4``, gradients
  ``rtol=2e-3, atol=2e-4 * max|reference gradient|`` (measured: 1.4e-6 colour, 2e-5 depth, 1.1e-4 x max gradient);
- CUDA: gsplat's fast exp and its own backward: images ``atol=1e-3``, gradients ``rtol=2e-2, atol=2e-3 * max``.
With opacities up to 0.99 the boxes differ at tile borders by a Gaussian's tail beyond 3 sigma (alpha < 0.0111):
there only the mean image error (< 1e-4 stand-in, < 1e-3 CUDA) and the largest (< 0.0111 / < 0.05) are bounded.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers import gsplat_standin
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render import get_renderer
from eligsir_o3d.render.gsplat_backend import GsplatRenderer
from test_render_agreement import CAMERAS, PARAMS, assert_grads_close, edge_case_scene, look_at_pose, render_with_grads

pytest.importorskip("gsplat")

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat needs a CUDA device")
TOL = {"standin": dict(img=2e-5, rtol=2e-3, atol_frac=2e-4, mean=1e-4, max=0.0111, m2d=1e-4),
       "cuda": dict(img=1e-3, rtol=2e-2, atol_frac=2e-3, mean=1e-3, max=0.05, m2d=1e-3)}
VIEWS = {  # a centred camera on the axis, and an off-centre principal point seen from an oblique pose
    "axis": (CAMERAS[0], look_at_pose([0.0, 0.0, -3.0])),
    "oblique": (CAMERAS[1], look_at_pose([0.4, -0.3, -2.5], target=[0.1, 0.05, 0.0])),
}
BG = torch.tensor([0.2, 0.4, 0.6])


class Gsplat:
    """One way of running the gsplat backend: its renderer, device and tolerances."""

    def __init__(self, kind: str, monkeypatch):
        self.kind, self.tol = kind, TOL[kind]
        self.device = "cpu" if kind == "standin" else "cuda"
        self.sh_calls: list[int] = []
        if kind == "standin":
            gsplat_standin.patch(monkeypatch)
            import gsplat.rendering as rendering

            def spherical_harmonics(degree, dirs, coeffs, masks=None):  # records that gsplat evaluated the SH
                self.sh_calls.append(degree)
                return gsplat_standin.spherical_harmonics(degree, dirs, coeffs, masks)

            monkeypatch.setattr(rendering, "spherical_harmonics", spherical_harmonics)
            self.renderer = GsplatRenderer("cpu", rasterization=rendering.rasterization)
        else:
            from eligsir_o3d.render.availability import gsplat_status

            status = gsplat_status("cuda")
            if not status.usable:
                pytest.skip(f"gsplat cannot run on this CUDA machine: {status.reason}")
            self.renderer = get_renderer("gsplat", "cuda")
        self.reference = get_renderer("torch", self.device)

    def to(self, params):
        return {k: v.to(self.device) for k, v in params.items()}


@pytest.fixture(params=["standin", pytest.param("cuda", marks=[needs_cuda, pytest.mark.cuda])])
def gs(request, monkeypatch):
    return Gsplat(request.param, monkeypatch)


@pytest.mark.parametrize("view", VIEWS)
def test_images_and_gradients_match_the_reference(gs, view):
    camera, T = VIEWS[view]
    params, _ = edge_case_scene(seed=2, max_opacity=0.35)
    bg = BG.to(gs.device)
    ref, ref_g = render_with_grads(gs.reference, gs.to(params), camera, T, bg)
    out, g = render_with_grads(gs.renderer, gs.to(params), camera, T, bg)
    for name in ("color", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=gs.tol["img"], rtol=1e-4,
                                   msg=lambda m, name=name: f"{name}: {m}")
    assert_grads_close(g, ref_g, rtol=gs.tol["rtol"], atol_frac=gs.tol["atol_frac"])
    # gsplat culls what cannot reach alpha 1/255; its radii are per-axis extents, reduced to the larger one
    assert out.radii.dtype == torch.int32 and out.radii.shape == ref.radii.shape
    faint = params["opacities"].to(gs.device) < 1.0 / 255.0
    assert faint.any() and not out.visible[faint].any() and ref.visible[faint].any()
    both = out.visible & ref.visible
    torch.testing.assert_close(out.means2d[both], ref.means2d[both], atol=gs.tol["m2d"], rtol=1e-5)
    # rows of culled Gaussians are masked, not gsplat's uninitialised memory
    assert torch.isnan(out.means2d[~out.visible]).all() and torch.isfinite(out.means2d[out.visible]).all()
    culled = ~out.visible & ~ref.visible
    assert culled.any() and float(g["means"][culled].abs().max()) == 0.0


@pytest.mark.parametrize("view", VIEWS)
def test_high_opacity_scene(gs, view):
    """Opacities up to 0.99 and an opaque stack that ends compositing early: images, depth, alpha and gradients."""
    camera, T = VIEWS[view]
    params, _ = edge_case_scene(seed=3)
    bg = BG.to(gs.device)
    ref, ref_g = render_with_grads(gs.reference, gs.to(params), camera, T, bg)
    out, g = render_with_grads(gs.renderer, gs.to(params), camera, T, bg)
    assert float(ref.alpha.detach().max()) > 0.999  # compositing stops early somewhere
    for name in ("color", "alpha"):
        err = (getattr(out, name) - getattr(ref, name)).detach().abs()
        assert float(err.mean()) < gs.tol["mean"] and float(err.max()) < gs.tol["max"], (name, err.mean(), err.max())
    covered = (ref.alpha > 0.5) & (out.alpha > 0.5)
    assert float((out.depth - ref.depth)[covered].abs().mean()) < 10 * gs.tol["mean"]  # metres
    for k in PARAMS:
        assert torch.isfinite(g[k]).all(), k
        rel = float((g[k] - ref_g[k]).norm() / ref_g[k].norm())
        assert rel < 50 * gs.tol["atol_frac"], (k, rel)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_colour_is_evaluated_by_gsplat_and_matches(gs, degree):
    """SH coefficients [N, K, 3] go to gsplat with sh_degree (its kernel evaluates them from inverse(viewmats));
    colours and the gradients of the coefficients and means match the reference's sh.py evaluation."""
    camera, T = VIEWS["oblique"]
    params, _ = edge_case_scene(n=200, seed=5, max_opacity=0.35)
    k = (degree + 1) ** 2
    sh = 0.3 * torch.randn(200, k, 3, generator=torch.Generator().manual_seed(degree))
    sh[:, 0] = (params["colors"] - 0.5) / 0.28209479177387814
    params["colors"] = sh
    ref, ref_g = render_with_grads(gs.reference, gs.to(params), camera, T, BG.to(gs.device))
    out, g = render_with_grads(gs.renderer, gs.to(params), camera, T, BG.to(gs.device))
    torch.testing.assert_close(out.color, ref.color, atol=gs.tol["img"], rtol=1e-4)
    assert_grads_close(g, ref_g, rtol=gs.tol["rtol"], atol_frac=gs.tol["atol_frac"])
    if gs.kind == "standin":
        assert gs.sh_calls and set(gs.sh_calls) == {degree}
    # the higher bands really contribute: the DC band alone renders other colours
    dc = dict(params, colors=sh[:, :1].clone())
    flat = gs.renderer.render(**gs.to(dc), camera=camera, T_world_cam=T)
    assert float((flat.color - out.color.detach()).abs().max()) > 0.05


def test_an_empty_map_never_reaches_gsplat():
    """gsplat's projection launch divides by the Gaussian count: with none it raised SIGFPE and killed the process
    on an H200 (stop 50). An empty map (before the first seeds, a view that culled every row) renders without it."""
    def rasterization(*args, **kwargs):
        raise AssertionError("gsplat called with no Gaussians")

    camera, T = VIEWS["axis"]
    out = GsplatRenderer("cpu", rasterization=rasterization).render(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3), camera, T, BG)
    torch.testing.assert_close(out.color, BG.expand_as(out.color))
    assert out.radii.shape == (0,) and out.means2d.shape == (0, 2) and torch.all(out.alpha == 0)


def test_empty_map_and_no_grad(gs):
    camera, T = VIEWS["oblique"]
    empty = dict(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 3), opacities=torch.zeros(0),
                 colors=torch.zeros(0, 3))
    out = gs.renderer.render(**gs.to(empty), camera=camera, T_world_cam=T, background=BG.to(gs.device))
    assert out.color.shape == (camera.height, camera.width, 3) and out.radii.shape == (0,)
    torch.testing.assert_close(out.color, BG.to(gs.device).expand_as(out.color))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    params, _ = edge_case_scene(n=150, seed=8, max_opacity=0.35)
    ps = {k: v.requires_grad_(True) for k, v in gs.to(params).items()}
    with torch.no_grad():
        quiet = gs.renderer.render(**ps, camera=camera, T_world_cam=T, background=BG.to(gs.device))
    assert not quiet.color.requires_grad and not quiet.depth.requires_grad
    live = gs.renderer.render(**ps, camera=camera, T_world_cam=T, background=BG.to(gs.device))
    assert live.color.requires_grad
    torch.testing.assert_close(quiet.color, live.color.detach(), atol=0, rtol=0)
    torch.testing.assert_close(quiet.depth, live.depth.detach(), atol=0, rtol=0)


def test_stand_in_catches_a_broken_convention(monkeypatch):
    """The comparison above is sharp: with camera-to-world passed as viewmats, or without the +0.5 principal-point
    shift, the stand-in's images leave the reference by far more than the tolerance."""
    import eligsir_o3d.render.gsplat_backend as backend

    gs = Gsplat("standin", monkeypatch)
    camera, T = VIEWS["oblique"]
    params, _ = edge_case_scene(seed=2, max_opacity=0.35)
    ref = gs.reference.render(**params, camera=camera, T_world_cam=T, background=BG)
    good = gs.renderer.render(**params, camera=camera, T_world_cam=T, background=BG)
    assert float((good.color - ref.color).abs().max()) < 2e-5
    # the renderer keeps recent views' viewmats/Ks on the device: another pose and camera must not hit that entry
    cam2, T2 = VIEWS["axis"]
    other = gs.renderer.render(**params, camera=cam2, T_world_cam=T2, background=BG)
    ref2 = gs.reference.render(**params, camera=cam2, T_world_cam=T2, background=BG)
    assert float((other.color - ref2.color).abs().max()) < 2e-5
    cam_to_world = lambda T, device, dtype: torch.as_tensor(np.asarray(T), dtype=dtype, device=device)  # noqa: E731
    no_shift = lambda cam, device: torch.tensor([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])  # noqa
    for name, broken in (("world_to_cam", cam_to_world), ("gsplat_intrinsics", no_shift)):
        with monkeypatch.context() as m:
            m.setattr(backend, name, broken)
            fresh = GsplatRenderer("cpu", rasterization=gs.renderer._rasterization)  # nothing cached yet
            bad = fresh.render(**params, camera=camera, T_world_cam=T, background=BG)
        assert float((bad.color - ref.color).abs().max()) > 1e-2, name


def _checker_rgbd(w=48, h=36):
    import open3d as o3d

    u, v = np.meshgrid(np.arange(w), np.arange(h))
    color = (((u // 6 + v // 6) % 2)[..., None] * np.array([180, 40, 60]) + 50).astype(np.uint8)
    depth = np.full((h, w), 1500, np.uint16)
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(depth)), color


def test_reconstructor_maps_through_gsplat(gs):
    """End to end with map-guided views and targeted growth with MCMC (relocation rounds every 10 updates, position
    noise every update): the map learns the scene. Full-resolution supervision (fidelity ablated): the checker
    would alias at this tiny size."""
    import open3d as o3d

    import eligsir_o3d as eo3d

    rgbd, color = _checker_rgbd()
    intrinsic = o3d.camera.PinholeCameraIntrinsic(48, 36, 40.0, 40.0, 23.5, 17.5)
    cfg = eo3d.Config(renderer="torch" if gs.kind == "standin" else "gsplat", ablate=("fidelity",))
    cfg.clock.mode, cfg.clock.updates_per_frame = "updates", 6
    cfg.growth.seed_stride = 1  # the probe of a 48x36 view is 12x9 pixels: seed every one
    cfg.growth.mcmc.refine_start = cfg.growth.mcmc.refine_every = 10
    rec = eo3d.Reconstructor(intrinsic, gs.device, cfg)
    if gs.kind == "standin":
        rec.renderer = gs.renderer
    rec.warmup()

    def psnr():
        out = rec.render(np.eye(4))
        return float(-10 * torch.log10(((out.color.cpu() - torch.from_numpy(color) / 255.0) ** 2).mean()))

    rec.integrate(rgbd, np.eye(4), timestamp=0.0)
    before = psnr()
    for i in range(1, 5):
        T = np.eye(4)
        T[0, 3] = 0.002 * i  # small moves: the views stay on the same wall
        rec.integrate(rgbd, T, timestamp=i / 30.0)
    after = psnr()
    assert after > before + 1.0, (before, after)
    assert rec.gmap.device.type == gs.device and all(torch.isfinite(p).all() for p in rec.gmap.params.values())
    assert rec.growth.mcmc.rng.device.type == gs.device  # position noise drawn where the map lives
    assert rec.growth.mcmc.counts["added"] > 0  # relocation/densification rounds ran
