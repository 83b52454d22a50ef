"""The numba kernel set's fused stages against the torch reference: the activated gather is ``render_args`` of the
raw rows, the fused loss handed to the renderer gives the leaves torch's gradients, and the one-pass step (chain
rule, regulariser, Adam, position noise) is the torch set's step of the same rows; rows out of view keep their bits."""

import pytest
import torch
from helpers.device_step import CAM, make_map, pose

from eligsir_o3d.core.gaussians import PARAM_NAMES
from eligsir_o3d.kernels import StepTerms
from eligsir_o3d.kernels.base import RowView, moments
from eligsir_o3d.kernels.cpu import NumbaKernels, regulariser
from eligsir_o3d.kernels.reference import TorchKernels
from eligsir_o3d.optim.losses import LossConfig
from eligsir_o3d.render.cpu_backend import CpuRenderer

LEAVES = ("means", "quats", "scales", "opacities", "colors")


def _raw_view(gm, idx):
    """The torch set's view of the rows ``idx``: raw leaves, activated by autograd in ``render_args``."""
    return RowView(gm, idx, {n: gm.params[n].detach()[idx].requires_grad_() for n in PARAM_NAMES}, activated=False)


def _images(seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(CAM.height, CAM.width, 3, generator=g),
            torch.rand(CAM.height, CAM.width, generator=g) + 1.0)


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_select_gathers_the_rows_activated(sh_degree):
    gm = make_map(400, seed=1, sh_degree=sh_degree)
    view = NumbaKernels().select(gm, CAM, pose(0.3))
    assert view.activated and 40 < len(view) < len(gm)
    want = _raw_view(gm, view.idx).render_args()
    for name, got, w in zip(LEAVES, view.render_args(), want):
        assert got.is_leaf and got.requires_grad, name
        torch.testing.assert_close(got, w.detach(), rtol=1e-6, atol=1e-7, msg=name)
    assert not NumbaKernels().select(gm, CAM, pose(0.3), grad=False).leaves["means"].requires_grad


@pytest.mark.parametrize("sh_degree", [0, 1])
@pytest.mark.parametrize("background", [None, (0.1, 0.2, 0.3)])
def test_backward_gives_the_leaves_torchs_gradients(sh_degree, background):
    gm = make_map(300, seed=2, sh_degree=sh_degree)
    T, bg = pose(0.3), None if background is None else torch.tensor(background)
    color, depth = _images()
    view = NumbaKernels().select(gm, CAM, T)
    NumbaKernels().backward(CpuRenderer().render(*view.render_args(), CAM, T, bg), color, depth, LossConfig(),
                            view, StepTerms())
    args = [a.detach().clone().requires_grad_() for a in view.render_args()]
    TorchKernels().backward(CpuRenderer().render(*args, CAM, T, bg), color, depth, LossConfig(), view,
                            StepTerms())  # the torch loss, autograd all the way
    for name, a in zip(LEAVES, args):
        got = view.leaves[name].grad
        torch.testing.assert_close(got, a.grad, rtol=1e-4, atol=1e-5 * float(a.grad.abs().max()) + 1e-12,
                                   msg=name)


def _leaf_grads(view, seed):
    g = torch.Generator().manual_seed(seed)
    for t in view.leaves.values():
        t.grad = torch.randn(t.shape, generator=g)


@pytest.mark.parametrize("sh_degree", [0, 1])
@pytest.mark.parametrize("regs,scaler", [((0.0, 0.0), 0.0), ((0.01, 0.02), 0.0), ((0.01, 0.02), 5e-3)])
def test_step_is_the_torch_sets_step(sh_degree, regs, scaler):
    """The same leaf gradients into both sets (the torch set's through autograd's activations and regulariser),
    three steps: parameters and moments agree, the rows out of view are untouched."""
    mine, ref = make_map(300, seed=3, sh_degree=sh_degree), make_map(300, seed=3, sh_degree=sh_degree)
    T = pose(0.3)
    gens = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    for step in range(3):
        before = {n: mine.params[n].detach().clone() for n in PARAM_NAMES}
        view = NumbaKernels().select(mine, CAM, T)
        _leaf_grads(view, step)
        rview = _raw_view(ref, view.idx)
        args = rview.render_args()
        total = sum((a * view.leaves[n].grad).sum() for n, a in zip(LEAVES, args))
        reg = regulariser(rview, StepTerms(*regs))
        (total if reg is None else total + reg).backward()
        NumbaKernels().step(mine, view, StepTerms(*regs, scaler, gens[0]))
        TorchKernels().step(ref, rview, StepTerms(*regs, scaler, gens[1]))
        out = torch.ones(len(mine), dtype=torch.bool)
        out[view.idx] = False
        for n in PARAM_NAMES:
            got, want = mine.params[n].detach(), ref.params[n].detach()
            assert torch.equal(got[out], before[n][out]), n
            tol = dict(rtol=1e-4, atol=1e-5) if n == "means" else dict(rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(got, want, **tol, msg=n)
            for m_got, m_want in zip(moments(mine, n), moments(ref, n)):
                # sigmoid's slope (1 - o) o of a saturated opacity carries the rounding of o, relative to 1 - o
                scale = float(m_want.abs().max()) if m_want.numel() else 0.0
                torch.testing.assert_close(m_got, m_want, rtol=1e-5, atol=1e-6 * scale + 1e-12, msg=n)
        assert mine.adam.steps == ref.adam.steps


def test_step_of_an_empty_view_counts_and_writes_nothing_but_draws_no_noise():
    gm = make_map(50, seed=4)
    T = pose(0.0)
    T[2, 3] = 50.0  # every row behind the camera
    view = NumbaKernels().select(gm, CAM, T)
    assert len(view) == 0
    before = {n: gm.params[n].detach().clone() for n in PARAM_NAMES}
    gen = torch.Generator().manual_seed(1)
    state = gen.get_state()
    NumbaKernels().step(gm, view, StepTerms(0.01, 0.01, 1e-3, gen))
    assert all(torch.equal(gm.params[n].detach(), before[n]) for n in PARAM_NAMES)
    assert torch.equal(gen.get_state(), state)
