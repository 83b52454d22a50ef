"""Threads while mapping on the CPU: torch's own operations run on ``optim.torch_threads`` (1 by default) inside
integrate/optimize and the caller's count is restored after; a compiled kernel over little work runs on one numba
thread (runtime.jit.threads_for), with the same bits as on all of them."""

import numba
import numpy as np
import pytest
import torch

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.runtime.jit import threads_for
from eligsir_o3d.runtime.threads import TORCH_MIN_PIXELS, TORCH_MIN_ROWS, torch_threads
from eligsir_o3d.datasets.synthetic import SyntheticRoom


@pytest.fixture
def two_torch_threads():
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(old)


def test_torch_threads_sets_and_restores(two_torch_threads):
    with torch_threads(1):
        assert torch.get_num_threads() == 1
        with torch_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with torch_threads(0):  # 0: leave torch's own setting
        assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("an update that fails")
    assert torch.get_num_threads() == 2  # restored on the way out of an error too


@pytest.mark.parametrize("setting, small", [(1, 1), (0, 2)])
def test_the_mapper_runs_torch_on_the_configured_threads(two_torch_threads, setting, small):
    seq = SyntheticRoom(n_frames=4, width=480, height=320)  # 153.6k pixels: at scale 1, past TORCH_MIN_PIXELS
    assert seq.camera.width * seq.camera.height >= TORCH_MIN_PIXELS
    cfg = Config(renderer="cpu")
    cfg.optim.torch_threads = setting
    rec = Reconstructor(seq.camera, "cpu", cfg, depth_scale=seq.depth_scale)
    seen, update = [], rec._update

    def spy(frame, sample):
        seen.append((sample.camera.pixels, torch.get_num_threads()))
        return update(frame, sample)

    rec._update = spy
    for item in seq:
        rec.integrate(item.rgbd, item.T_world_cam, updates=1)  # at the fidelity policy's scale (small here)
        assert torch.get_num_threads() == 2  # the caller's count, back after every call
    rec.optimize(1, scale=1.0)
    assert torch.get_num_threads() == 2
    assert {t for px, t in seen if px < TORCH_MIN_PIXELS} == {small}
    assert {t for px, t in seen if px >= TORCH_MIN_PIXELS} == {2}  # a large image keeps the caller's threads
    seen.clear()
    rec.last_in_view = TORCH_MIN_ROWS  # as after an update with that many Gaussians in view
    rec._step(0.25)
    assert seen[0][0] < TORCH_MIN_PIXELS and seen[0][1] == 2  # many rows in view: the caller's threads too


def test_a_small_kernel_runs_on_one_numba_thread_with_the_same_bits():
    n = numba.get_num_threads()
    with threads_for(10, 100):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == n
    with threads_for(100, 100):
        assert numba.get_num_threads() == n
    # D-SSIM's kernel on one thread and on all of them: the same value and gradient, bit for bit
    from eligsir_o3d.optim.dssim_kernels import dssim_value_and_grad

    rng = np.random.default_rng(0)
    x, y = rng.random((2, 3, 60, 80), dtype=np.float32)
    win = np.exp(-0.5 * ((np.arange(11) - 5) / 1.5) ** 2).astype(np.float32)
    win /= win.sum()
    out = []
    for work in (0, 1):
        grad = np.empty_like(x)
        with threads_for(work, 1):
            value = dssim_value_and_grad(x, y, win, grad)
        out.append((value, grad))
    assert out[0][0] == out[1][0] and np.array_equal(out[0][1], out[1][1])
