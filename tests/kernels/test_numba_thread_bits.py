"""The numba kernel set's fused stages give the same bits whatever their loops' thread layout: chained updates
(gather, render, fused loss, backward, step with position noise) on one numba thread equal those on two, and the
parallel kernels equal the same kernels compiled serial (a loop split over threads or vectorised differently must
not round differently, or maps would differ between machines with different core counts)."""

import numba
import pytest
import torch
from helpers.device_step import CAM, make_map, pose

from eligsir_o3d.core.gaussians import PARAM_NAMES
from eligsir_o3d.kernels import StepTerms
from eligsir_o3d.kernels.base import moments
from eligsir_o3d.kernels.cpu import NumbaKernels
from eligsir_o3d.optim.losses import LossConfig
from eligsir_o3d.render.cpu_backend import CpuRenderer

ROWS = 3001  # odd: every thread's share and the vector loops leave a remainder


def _updates(n_updates=3, sh_degree=0):
    """The map's parameters and moments after ``n_updates`` updates of the numba set at alternating poses."""
    gm = make_map(ROWS, seed=11, sh_degree=sh_degree, spread=1.0)
    g = torch.Generator().manual_seed(12)
    color = torch.rand(CAM.height, CAM.width, 3, generator=g)
    depth = torch.rand(CAM.height, CAM.width, generator=g) + 1.5
    gen = torch.Generator().manual_seed(13)
    ks = NumbaKernels()
    for u in range(n_updates):
        T = pose(0.1 * (u % 2))
        view = ks.select(gm, CAM, T)
        assert len(view) > ROWS // 2
        out = CpuRenderer().render(*view.render_args(), CAM, T, None)
        terms = StepTerms(0.01, 0.02, 5e-3, gen)
        ks.backward(out, color, depth, LossConfig(), view, terms)
        ks.step(gm, view, terms)
    state = {n: gm.params[n].detach().clone() for n in PARAM_NAMES}
    state.update({f"{n}.m{i}": t.clone() for n in PARAM_NAMES for i, t in enumerate(moments(gm, n))})
    return state


def _assert_same_bits(a, b):
    assert a.keys() == b.keys()
    for n in a:
        assert torch.equal(a[n].view(torch.int32), b[n].view(torch.int32)), n


@pytest.fixture
def every_kernel_parallel(monkeypatch):
    """The row and pixel kernels on numba's threads at any size (the set narrows small work to one thread)."""
    from eligsir_o3d.runtime import jit

    monkeypatch.setattr(jit, "ROWS_LIMIT", 0)
    monkeypatch.setattr(jit, "PARALLEL_MIN_PIXELS", 0)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba's pool has one thread")
@pytest.mark.parametrize("sh_degree", [0, 1])
def test_one_thread_gives_the_bits_of_two(every_kernel_parallel, sh_degree):
    n = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _updates(sh_degree=sh_degree)
        numba.set_num_threads(2)
        two = _updates(sh_degree=sh_degree)
    finally:
        numba.set_num_threads(n)
    _assert_same_bits(one, two)


def test_the_parallel_kernels_give_the_bits_of_serial_ones(every_kernel_parallel, monkeypatch):
    """The gather, the step, the position noise and the fused loss's kernels compiled without ``parallel`` (prange
    is range: one loop, vectorised or not as LLVM sees fit) against the parallel ones."""
    from eligsir_o3d.kernels import cpu_kernels
    from eligsir_o3d.optim import loss_kernels, update_kernels

    parallel = _updates()
    for mod, name in ((cpu_kernels, "gather_activated"), (cpu_kernels, "step_view"),
                      (update_kernels, "_noise_view"), (loss_kernels, "loss_terms"), (loss_kernels, "loss_grad")):
        monkeypatch.setattr(mod, name, numba.njit(parallel=False, fastmath=False)(getattr(mod, name).py_func))
    _assert_same_bits(parallel, _updates())
