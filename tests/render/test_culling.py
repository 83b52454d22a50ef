"""View-culled updates (eligsir_o3d.render.culling, the kernel sets' select and step): the culled render equals the
map's render (the torch reference is the oracle), the compiled and torch kernel sets step the rows alike, and an
update leaves the rows out of view untouched."""

import numpy as np
import pytest
import torch

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render.culling import in_view
from eligsir_o3d.kernels import StepTerms, get_kernels
from eligsir_o3d.kernels.base import RowView, moments
from eligsir_o3d.kernels.cpu import gather_raw
from eligsir_o3d.core.frame import Frame
from eligsir_o3d.core.gaussians import PARAM_NAMES, GaussianMap
from eligsir_o3d.render import get_renderer

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def _map(n=2000, seed=0, spread=2.0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * spread
    means[:, 2] += 2.0
    gm = GaussianMap(0)
    gm.add(means, torch.rand(n, 3, generator=g), torch.rand(n, generator=g) * 0.2 + 0.01, 0.5,
           torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))
    return gm


def _pose(yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [0.1, -0.05, 0.0]
    return T


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_view_leaves_are_the_maps_rows_as_new_leaves(sh_degree):
    gm = GaussianMap(sh_degree)
    g = torch.Generator().manual_seed(4)
    gm.add(torch.randn(300, 3, generator=g), torch.rand(300, 3, generator=g), torch.rand(300, generator=g) * 0.2 + 0.01,
           0.5, torch.nn.functional.normalize(torch.randn(300, 4, generator=g), dim=-1))
    for idx in (torch.tensor([], dtype=torch.long), torch.tensor([299, 0, 17, 5]), torch.arange(300)):
        view = RowView(gm, idx, gather_raw(gm, idx, True), activated=False)
        for name in PARAM_NAMES:
            leaf, p = view.leaves[name], gm.params[name].detach()
            assert leaf.requires_grad and leaf.is_leaf and leaf.grad is None
            assert leaf.shape == (len(idx),) + p.shape[1:] and torch.equal(leaf, p[idx])
            assert leaf.data_ptr() != p.data_ptr() or leaf.numel() == 0  # a copy: the map is not written through it


@pytest.mark.parametrize("renderer,kernels", [("torch", "torch"), ("cpu", "numba"), ("cpu", "torch")])
def test_culled_render_equals_map_render_images_and_gradients(renderer, kernels):
    gm = _map()
    r = get_renderer(renderer, "cpu")
    T = _pose(0.3)
    target = torch.rand(CAM.height, CAM.width, 3, generator=torch.Generator().manual_seed(1))

    if kernels == "numba":  # activated leaves: every row through the set's own gather (the same activations)
        leaves = get_kernels(kernels).select(gm, CAM, T, cull=False).leaves
        full = tuple(leaves[n] for n in ("means", "quats", "scales", "opacities", "colors"))
    else:
        leaves = {n: gm.params[n].detach().clone().requires_grad_(True) for n in PARAM_NAMES}
        full = (leaves["means"], leaves["quats"], torch.exp(leaves["scales"]), torch.sigmoid(leaves["opacities"]),
                torch.clamp_min(leaves["sh0"][:, 0] * 0.28209479177387814 + 0.5, 0.0))
    out = r.render(*full, CAM, T)
    ((out.color - target).abs().mean() + out.depth.mean() + out.alpha.mean()).backward()

    view = get_kernels(kernels).select(gm, CAM, T)
    assert 0 < len(view) < len(gm)  # the test map reaches beyond the view
    out_c = r.render(*view.render_args(), CAM, T)
    ((out_c.color - target).abs().mean() + out_c.depth.mean() + out_c.alpha.mean()).backward()

    assert torch.equal(out.color, out_c.color) and torch.equal(out.depth, out_c.depth)
    assert torch.equal(out.alpha, out_c.alpha)
    drawn = torch.nonzero(out.radii > 0).squeeze(1)
    assert bool(torch.isin(drawn, view.idx).all())  # every Gaussian the renderer draws is kept
    out_rows = torch.ones(len(gm), dtype=torch.bool)
    out_rows[view.idx] = False
    for n in ("means", "quats", "scales", "opacities", "colors" if view.activated else "sh0"):
        torch.testing.assert_close(view.leaves[n].grad, leaves[n].grad[view.idx], rtol=1e-5, atol=1e-9)
        assert not leaves[n].grad[out_rows].any()  # the rows dropped have no gradient in the map's render


def test_compiled_view_test_keeps_the_torch_bound_and_little_more():
    """The compiled test (float32, the scale bounded within 6%) keeps every row the float64 torch bound keeps and
    none that the torch bound with 7% larger scales drops."""
    gm = _map(5000, seed=3, spread=3.0)
    for yaw in (0.0, 1.0, 2.5):
        fast = in_view(gm.params["means"], gm.params["scales"], CAM, _pose(yaw))
        exact = in_view(gm.params["means"].double(), gm.params["scales"].double(), CAM, _pose(yaw))
        loose = in_view(gm.params["means"].double(), gm.params["scales"].double() + np.log(1.07), CAM, _pose(yaw))
        assert bool(torch.isin(exact, fast).all()) and bool(torch.isin(fast, loose).all())
        assert len(exact) > 100


def test_view_adam_on_rows_stepped_every_update_is_torch_adam():
    """Rows in view in every update end where torch's Adam ends after the same gradients (the tensor's step count
    is then every row's)."""
    gm = _map(50)
    rng = torch.Generator().manual_seed(5)
    idx = torch.arange(0, 50, 2)
    start = gm.params["sh0"].detach()[idx].clone()
    p = torch.nn.Parameter(start.clone())
    opt = torch.optim.Adam([p], lr=gm.lrs.sh0, betas=(0.9, 0.999), eps=1e-15)
    kernels = get_kernels("numba")
    for _ in range(6):
        view = RowView(gm, idx, gather_raw(gm, idx, True), activated=False)
        g = torch.randn(len(idx), 1, 3, generator=rng)
        view.leaves["sh0"].grad = g
        kernels.step(gm, view, StepTerms())
        p.grad = g.clone()
        opt.step()
    torch.testing.assert_close(gm.params["sh0"].detach()[idx], p.detach(), rtol=2e-6, atol=1e-7)
    others = torch.ones(50, dtype=torch.bool)
    others[idx] = False
    assert not moments(gm, "sh0")[0][others].any()  # rows never in view: no moments


def _scene_rec(tmp_cull=True):
    cfg = Config(renderer="cpu", seed=0)
    cfg.optim.cull = tmp_cull
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 2, 2  # a relocation round within the test
    rec = Reconstructor(CAM, "cpu", cfg)
    gm = _map(3000, seed=2, spread=2.5)
    gm.params["opacities"].data[::7] = -9.0  # dead Gaussians (in view and out of it) for the relocation
    rec.gmap = gm
    T = _pose(0.2)
    color = torch.rand(CAM.height, CAM.width, 3, generator=torch.Generator().manual_seed(4))
    depth = torch.full((CAM.height, CAM.width), 2.0)
    rec.views.retain(Frame(color, depth, CAM, T, 0.0, 0))
    return rec, T


def test_update_leaves_rows_out_of_view_bit_for_bit_untouched():
    rec, T = _scene_rec()
    rec.optimize(1, scale=1.0)  # Adam state exists from here on
    idx = in_view(rec.gmap.params["means"], rec.gmap.params["scales"], CAM, T)
    Tt = torch.as_tensor(T, dtype=torch.float32)
    z_cam = (rec.gmap.params["means"].detach() - Tt[:3, 3]) @ Tt[:3, 2]
    out_rows = z_cam < -0.5  # well behind the camera: out of view in every update of the test
    assert out_rows.sum() > 100 and not bool(torch.isin(torch.nonzero(out_rows).squeeze(1), idx).any())
    n0 = len(rec.gmap)
    before = {n: rec.gmap.params[n].detach()[:n0][out_rows].clone() for n in PARAM_NAMES}
    saved = {n: [m[:n0][out_rows].clone() for m in moments(rec.gmap, n)] for n in PARAM_NAMES}
    rec.optimize(4, scale=1.0)  # includes relocation and densification rounds and the noise
    assert rec.growth.mcmc.counts["relocated"] > 0
    rec.gmap.check_aligned()
    for n in PARAM_NAMES:
        assert torch.equal(rec.gmap.params[n].detach()[:n0][out_rows], before[n]), n
        for k, (m, v) in enumerate(zip(moments(rec.gmap, n), saved[n])):
            assert torch.equal(m[:n0][out_rows], v), (n, k)
    assert moments(rec.gmap, "sh0")[1][idx].any()  # the view's rows were stepped


def test_relocation_resets_the_moments_of_the_relocated_rows():
    rec, T = _scene_rec()
    dead = torch.nonzero(torch.sigmoid(rec.gmap.params["opacities"].detach()) <= 0.005).squeeze(1)
    idx = in_view(rec.gmap.params["means"], rec.gmap.params["scales"], CAM, T)
    dead_in_view = dead[torch.isin(dead, idx)]
    assert len(dead_in_view) > 0
    rec.optimize(2, scale=1.0)  # update 2 is a refinement round: relocated rows get zeroed moments
    assert rec.growth.mcmc.counts["relocated"] > 0
    m, v = moments(rec.gmap, "means")
    assert not v[dead_in_view].any() and v[idx].any()


def test_culled_and_unculled_updates_agree_on_a_map_in_view():
    """With every Gaussian in view, culling changes nothing: per-row step counts equal torch's global count when
    every row is stepped in every update. (Noise draws differ; the regularisers are off because they step rows
    whose footprint shrinks out of the view bound, which the map-wide update steps and the culled one does not.)"""
    recs = []
    for cull in (True, False):
        rec, T = _scene_rec(cull)
        rec.config.growth.mcmc.noise_lr = 0.0
        rec.config.growth.mcmc.refine_start = 10 ** 6
        rec.config.growth.mcmc.opacity_reg = rec.config.growth.mcmc.scale_reg = 0.0
        keep = in_view(rec.gmap.params["means"], rec.gmap.params["scales"], CAM, T)
        mask = torch.zeros(len(rec.gmap), dtype=torch.bool)
        mask[keep] = True
        rec.gmap.remove(~mask)
        rec.optimize(3, scale=1.0)
        recs.append(rec)
    for n in PARAM_NAMES:
        torch.testing.assert_close(recs[0].gmap.params[n].detach(), recs[1].gmap.params[n].detach(),
                                   rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("noise", [0.0, 50.0])
def test_numba_and_torch_kernel_sets_step_the_same_rows_alike(noise):
    """The numba set's step (one compiled Adam pass, the noise where the rows lie) equals the torch set's over
    views that overlap: parameters and moments to float32 rounding, the rows out of every view untouched."""
    def run(name: str) -> GaussianMap:
        gm = _map(300, seed=3)
        kernels = get_kernels(name)
        rng, noise_rng = torch.Generator().manual_seed(9), torch.Generator().manual_seed(2)
        for _ in range(5):
            idx = torch.nonzero(torch.rand(len(gm), generator=rng) < 0.6).squeeze(1)
            view = RowView(gm, idx, gather_raw(gm, idx, True), activated=False)
            for leaf in view.leaves.values():
                if leaf.numel():
                    leaf.grad = torch.randn(leaf.shape, generator=rng)
            kernels.step(gm, view, StepTerms(noise_scaler=noise, generator=noise_rng))
        return gm

    a, b = run("numba"), run("torch")
    for name in PARAM_NAMES:
        torch.testing.assert_close(a.params[name], b.params[name], rtol=1e-5, atol=1e-6)
        for ma, mb in zip(moments(a, name), moments(b, name)):
            torch.testing.assert_close(ma, mb, rtol=1e-5, atol=1e-7)
