"""The Triton stages of the device step (eligsir_o3d.kernels.triton_*) against their torch references, run by
Triton's interpreter on CPU tensors; their launch counts; and each kernel compiled for a CUDA target (no GPU
needed: Triton compiles to a cubin on the CPU)."""

import pytest
import torch
from helpers.device_step import make_map, pose, view_scalars

from eligsir_o3d.core.gaussians import PARAM_NAMES
from eligsir_o3d.kernels import device_reference as ref

triton = pytest.importorskip("triton")

from eligsir_o3d.kernels import triton_step  # noqa: E402
from eligsir_o3d.kernels.triton_launch import counting  # noqa: E402


def _selection(gm, T, extra):
    V, cam = view_scalars(T)
    p = {n: gm.params[n].detach() for n in PARAM_NAMES}
    args = (p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"], p["shN"], V, cam)
    n_hits = int(ref.select_rows(*args, 1, gm.sh_degree).count)
    return ref.select_rows(*args, max(n_hits + extra, 0), gm.sh_degree)


def _state(gm, seed):
    g = torch.Generator().manual_seed(seed)
    p = {n: gm.params[n].detach().clone() for n in PARAM_NAMES}
    m = {n: torch.randn(t.shape, generator=g) * 0.01 for n, t in p.items()}
    v = {n: torch.rand(t.shape, generator=g) * 1e-4 for n, t in p.items()}
    return p, m, v


@pytest.mark.parametrize("sh_degree", [0, 1])
@pytest.mark.parametrize("extra,drop,scaler", [(5, (), 5e3), (-10, (), 0.0), (0, ("means", "colors"), 1e3),
                                               (3, ("quats", "scales", "opacities"), 0.0)])
def test_step_kernel_is_the_reference(sh_degree, extra, drop, scaler):
    gm = make_map(300, seed=3, sh_degree=sh_degree)
    sel = _selection(gm, pose(0.3), extra)
    C = sel.idx.shape[0]
    g = torch.Generator().manual_seed(7)
    grads = {k: torch.randn(t.shape, generator=g) for k, t in zip(("means", "quats", "scales", "opacities",
                                                                    "colors"), sel[2:]) if k not in drop}
    z = torch.randn(C, 3, generator=g)
    adam = {n: ref.adam_scalars(0.01 * (i + 1), 0.9, 0.999, 1e-15, 3) for i, n in enumerate(PARAM_NAMES)}
    states = [_state(gm, 1), _state(gm, 1)]
    regs = dict(opacity_reg=0.01, scale_reg=0.02, n_map=len(gm), scaler=scaler, z=z)
    ref.step_rows(*states[0], sel.idx, sel.count, grads, adam, **regs)
    with counting() as c:
        triton_step.step_rows(*states[1], sel.idx, sel.count, grads, adam, **regs)
    assert c.n == 1
    for want, got in zip(*states):
        for n in PARAM_NAMES:
            torch.testing.assert_close(got[n], want[n], rtol=1e-5, atol=1e-6)  # the noise: float32 rounding


@pytest.mark.parametrize("sh_degree", [0, 2])
@pytest.mark.parametrize("n,extra,away", [(3000, 7, False), (3000, -25, False), (3000, 0, False), (50, 5, True),
                                          (0, 4, False)])
def test_select_kernels_are_the_reference(sh_degree, n, extra, away):
    from eligsir_o3d.kernels import triton_select

    gm = make_map(n, seed=2, sh_degree=sh_degree)
    T = pose(0.3)
    if away:
        T[2, 3] = 50.0  # every row behind the camera
    V, cam = view_scalars(T)
    p = [gm.params[k].detach() for k in ("means", "scales", "quats", "opacities", "sh0", "shN")]
    n_hits = int(ref.select_rows(*p, V, cam, 1, sh_degree).count)
    assert (n_hits > 100) == (n > 1000)
    cap = max(n_hits + extra, 1)
    want = ref.select_rows(*p, V, cam, cap, sh_degree)
    with counting() as c:
        got = triton_select.select_rows(*p, V, cam, cap, sh_degree)
    assert c.n == 2  # + torch's cumsum: 3 launches
    for name, a, b in zip(want._fields, got, want):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        exact = name in ("idx", "count", "means", "quats")  # exp and sigmoid: to float32 rounding
        torch.testing.assert_close(a, b, rtol=0 if exact else 1e-6, atol=0)


def test_kernels_compile_for_cuda():
    """Every kernel as the stages launch it compiles for an sm_90 target (Triton builds the cubin without a
    GPU): what the interpreter ran is also valid compiled Triton."""
    from eligsir_o3d.kernels import triton_select
    from eligsir_o3d.kernels.triton_launch import compile_for_cuda, recording

    launches = []
    for sh_degree in (0, 1):
        gm = make_map(40, seed=1, sh_degree=sh_degree)
        p = {n: gm.params[n].detach() for n in PARAM_NAMES}
        V, cam = view_scalars(pose(0.3))
        with recording() as rec:
            sel = triton_select.select_rows(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"], p["shN"],
                                            V, cam, 16, sh_degree)
            grads = dict(zip(("means", "quats", "scales", "opacities", "colors"), sel[2:]))
            adam = {n: ref.adam_scalars(0.01, 0.9, 0.999, 1e-15, 1) for n in PARAM_NAMES}
            m = {n: torch.zeros_like(t) for n, t in p.items()}
            triton_step.step_rows(p, m, dict(m), sel.idx, sel.count, grads, adam, 0.1, 0.1, 40, 1.0,
                                  torch.zeros(16, 3))
        launches += rec
    assert len(launches) == 6
    for k, args, meta in launches:
        assert compile_for_cuda(k, args, dict(meta, BLOCK=128)).asm["cubin"], k.__name__


_WEIGHTS = [(0.2, 0.5, 0.5), (0.0, 0.5, 0.5), (0.2, 0.0, 0.5), (0.2, 0.5, 0.0), (0.2, 0.5, "no depth")]
_LOSS_CASES = [(hw, bg, w) for hw in [(7, 9), (3, 4), (2, 5)] for bg in (None, (0.2, 0.5, 0.9)) for w in _WEIGHTS]
_LOSS_CASES += [((30, 41), (0.2, 0.5, 0.9), _WEIGHTS[0]), ((30, 41), None, _WEIGHTS[4])]  # the full window


@pytest.mark.parametrize("hw,background,weights", _LOSS_CASES)
def test_loss_kernels_are_the_reference(hw, background, weights):
    from eligsir_o3d.kernels import device_reference_loss, triton_loss
    from helpers.device_step import accumulations

    acc, alpha, color, depth = accumulations(*hw, seed=hw[0])
    if weights[2] == "no depth":
        depth, weights = torch.zeros_like(depth), weights[:2] + (0.5,)
    bg = None if background is None else torch.tensor(background)
    want = device_reference_loss.fused_loss(acc, alpha, bg, color, depth, *weights)
    with counting() as c:
        got = triton_loss.fused_loss(acc, alpha, bg, color, depth, *weights)
    assert c.n == 2
    torch.testing.assert_close(got[0], want[0], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(got[1], want[1], rtol=1e-6, atol=1e-7)
    for g, w in zip(got[2:], want[2:]):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-6 * float(w.abs().max()) + 1e-12)
