"""The torch references of the device step (eligsir_o3d.kernels.device_reference*) against today's code: the rows
of ``in_view`` gathered and activated as ``RowView.render_args`` does, the loss of ``supervision_loss`` with its
gradient, and the numba kernel set's step (chain rule, regulariser, Adam) followed by ``mcmc_noise_rows``."""

import dataclasses
import inspect

import pytest
import torch
from helpers.device_step import CAM, accumulations, make_map, pose, view_scalars

from eligsir_o3d import kernels
from eligsir_o3d.core.gaussians import PARAM_NAMES
from eligsir_o3d.kernels import device_reference as ref
from eligsir_o3d.kernels.device_reference_loss import fused_loss
from eligsir_o3d.optim.losses import LossConfig, supervision_loss
from eligsir_o3d.optim.update_kernels import mcmc_noise_rows
from eligsir_o3d.render.base import RenderOutput, finish
from eligsir_o3d.render.culling import in_view
from eligsir_o3d.kernels import StepTerms
from eligsir_o3d.kernels.base import RowView, moments
from eligsir_o3d.kernels.cpu import NumbaKernels, gather_activated_rows, gather_raw


def _select(gm, T, capacity):
    V, cam = view_scalars(T)
    p = {n: gm.params[n].detach() for n in PARAM_NAMES}
    return ref.select_rows(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"], p["shN"], V, cam,
                           capacity, gm.sh_degree)


def _torch_in_view(gm, T):
    """``in_view``'s torch branch (float64), the bound select_rows keeps (the compiled CPU test is a superset)."""
    return in_view(gm.params["means"].detach().double(), gm.params["scales"].detach().double(), CAM, T)


@pytest.mark.parametrize("sh_degree", [0, 2])
@pytest.mark.parametrize("extra", [7, 0, -20])
def test_select_rows_are_in_view_gathered_and_activated(sh_degree, extra):
    gm = make_map(400, seed=1, sh_degree=sh_degree)
    T = pose(0.3)
    ids = _torch_in_view(gm, T)
    assert 40 < len(ids) < len(gm)
    cap = len(ids) + extra
    sel = _select(gm, T, cap)
    assert sel.count.shape == (1,) and int(sel.count) == len(ids)
    k = min(cap, len(ids))
    assert torch.equal(sel.idx[:k], ids[:k]) and not sel.idx[k:].any()
    args = RowView(gm, ids[:k], gather_raw(gm, ids[:k], True), activated=False).render_args()
    for got, want in zip(sel[2:], args):
        assert got.shape[0] == cap and torch.equal(got[:k], want.detach())
    pad = slice(k, None)
    assert not sel.means[pad].any() and not sel.opacities[pad].any() and not sel.colors[pad].any()
    assert (sel.scales[pad] == ref.PAD_SCALE).all() and (sel.quats[pad, 0] == 1).all()
    assert not sel.quats[pad, 1:].any()


def test_select_rows_without_hits_or_rows():
    gm = make_map(50, seed=2)
    T = pose(0.0)
    T[2, 3] = 50.0  # every row behind the camera
    assert len(_torch_in_view(gm, T)) == 0
    sel = _select(gm, T, 8)
    assert int(sel.count) == 0 and not sel.idx.any() and not sel.opacities.any()
    empty = make_map(0)
    sel = _select(empty, pose(0.0), 4)
    assert int(sel.count) == 0 and sel.means.shape == (4, 3) and (sel.quats[:, 0] == 1).all()


def _torch_loss(acc, alpha, bg, color, depth, cfg, fused_cpu):
    acc, alpha = acc.clone().requires_grad_(True), alpha.clone().requires_grad_(True)
    c, d, a = finish(acc[..., :3], acc[..., 3], alpha, bg)
    out = RenderOutput(c, d, a, torch.zeros(0, dtype=torch.int32), raw=(acc, alpha, bg) if fused_cpu else None)
    loss, error = supervision_loss(out, color, depth, cfg)
    loss.backward()
    g_alpha = torch.zeros_like(alpha) if alpha.grad is None else alpha.grad
    return loss.detach(), error, acc.grad, g_alpha


@pytest.mark.parametrize("hw", [(30, 41), (7, 9), (3, 4), (2, 5)])
@pytest.mark.parametrize("background", [None, (0.2, 0.5, 0.9)])
@pytest.mark.parametrize("change", [{}, {"lambda_dssim": 0.0}, {"lambda_depth": 0.0}, {"depth_alpha_min": 0.0},
                                    {"no_depth": True}])
def test_fused_loss_is_supervision_loss(hw, background, change):
    acc, alpha, color, depth = accumulations(*hw, seed=len(change))
    if change.pop("no_depth", False):
        depth = torch.zeros_like(depth)
    bg = None if background is None else torch.tensor(background)
    cfg = dataclasses.replace(LossConfig(), **change)
    got = fused_loss(acc, alpha, bg, color, depth, cfg.lambda_dssim, cfg.lambda_depth, cfg.depth_alpha_min)
    assert got[0].shape == () and got[1].shape == hw and got[2].shape == hw + (4,) and got[3].shape == hw
    for fused_cpu in (True, False):
        want = _torch_loss(acc, alpha, bg, color, depth, cfg, fused_cpu)
        torch.testing.assert_close(got[0], want[0], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(got[1], want[1], rtol=1e-6, atol=1e-7)
        for g, w in zip(got[2:], want[2:]):
            torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-6 * float(w.abs().max()) + 1e-12)


def _step_today(gm, ids, grads, regs, z, scaler):
    """The numba set's step of the rows ``ids`` from the activated leaves' gradients ``grads`` (chain rule,
    regulariser, Adam in one pass), then the noise of ``z`` by ``mcmc_noise_rows`` (the fused pass draws its own)."""
    view = RowView(gm, ids, gather_activated_rows(gm, ids, True), activated=True)
    for t, g in zip(view.render_args(), grads):
        t.grad = g
    NumbaKernels().step(gm, view, StepTerms(*regs))
    mcmc_noise_rows(gm.params, ids, z, scaler)


def _state(gm, name, key):
    return moments(gm, name)[0 if key == "exp_avg" else 1]


@pytest.mark.parametrize("sh_degree", [0, 1])
@pytest.mark.parametrize("yaw,extra", [(0.3, 5), (0.0, 0), (0.3, -10)])
def test_step_rows_is_todays_update_step(sh_degree, yaw, extra):
    gm, mine = make_map(300, seed=3, sh_degree=sh_degree), make_map(300, seed=3, sh_degree=sh_degree)
    T = pose(yaw)
    rng = torch.Generator().manual_seed(5)
    regs, scaler = (0.01, 0.02), 5e3
    params = {n: mine.params[n] for n in PARAM_NAMES}
    m = {n: torch.zeros_like(p.detach()) for n, p in params.items()}
    v = {n: torch.zeros_like(p.detach()) for n, p in params.items()}
    for step in (1, 2):
        sel = _select(mine, T, int(_select(mine, T, 1).count) + extra)
        C, k = sel.idx.shape[0], min(sel.idx.shape[0], int(sel.count))
        assert k > 20
        grads = [torch.randn(t.shape, generator=rng) for t in sel[2:]]  # padding rows: garbage, never read
        z = torch.randn(C, 3, generator=rng)
        _step_today(gm, sel.idx[:k], [g[:k] for g in grads], regs, z[:k], scaler)
        adam = {n: ref.adam_scalars(getattr(mine.lrs, n), 0.9, 0.999, mine.adam.eps, step) for n in PARAM_NAMES}
        before = {n: p.detach().clone() for n, p in params.items()}
        ref.step_rows(params, m, v, sel.idx, sel.count, dict(zip(("means", "quats", "scales", "opacities", "colors"),
                      grads)), adam, *regs, n_map=len(mine), scaler=scaler, z=z)
        out = torch.ones(len(mine), dtype=torch.bool)
        out[sel.idx[:k]] = False
        for n in PARAM_NAMES:
            assert torch.equal(params[n].detach()[out], before[n][out]), n  # rows out of view: bit for bit
            # the noise's gate, sigmoid(100 (1 - o) - 99.5) scaler, magnifies the opacity's rounding
            tol = dict(rtol=1e-4, atol=1e-5) if n == "means" else dict(rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(params[n].detach(), gm.params[n].detach(), **tol, msg=n)
            if params[n].numel():
                torch.testing.assert_close(m[n], _state(gm, n, "exp_avg"), rtol=1e-5, atol=1e-7)
                torch.testing.assert_close(v[n], _state(gm, n, "exp_avg_sq"), rtol=1e-5, atol=1e-9)


def test_step_rows_without_gradients_or_noise_writes_nothing():
    gm = make_map(60, seed=4)
    sel = _select(gm, pose(0.3), 64)
    params = {n: gm.params[n].detach() for n in PARAM_NAMES}
    before = {n: p.clone() for n, p in params.items()}
    zeros = {n: torch.zeros_like(p) for n, p in params.items()}
    ref.step_rows(params, zeros, dict(zeros), sel.idx, sel.count, {}, {}, n_map=60)
    assert all(torch.equal(params[n], before[n]) for n in PARAM_NAMES)


def test_reference_modules_stay_small():
    for mod in (ref, kernels.device_reference_loss):
        src = inspect.getsource(mod)
        assert len(src.splitlines()) <= 350, mod.__name__
        for name, fn in inspect.getmembers(mod, inspect.isfunction):
            if fn.__module__ == mod.__name__:
                assert len(inspect.getsource(fn).splitlines()) <= 80, name
