"""Threads that pay on the CPU. The package waits passively for OpenMP work (:func:`eligsir_o3d.runtime.prepare`: spinning
workers starve the main thread of a busy machine), so every parallel region wakes sleeping workers: ~55-60 us per
region on the 2-core machines measured (a 2-thread region of trivial work; 1.5 us on one thread). A parallel step
shorter than ~0.2 ms loses more to the wake-up than a second thread saves, and a 1/4-scale mapping update is made
of dozens of such steps: torch's operations on a few thousand rows or a 160x120 image, and compiled kernels over
the Gaussians in view.

- :func:`torch_threads`: torch's thread count for a block (``optim.torch_threads``: 1 by default), used by the
  :class:`~eligsir_o3d.Reconstructor` for frames' admission and growth and for updates on images below
  :data:`TORCH_MIN_PIXELS` with fewer than :data:`TORCH_MIN_ROWS` Gaussians in view (the last update's);
  larger ones keep the caller's count (77k Gaussians in view at 1/4 scale: 0.96 of the time on 2 threads, 16k even);
- :func:`.jit.threads_for`: one numba thread for a kernel over less than :data:`PARALLEL_MIN_ROWS` Gaussians
  (:data:`PARALLEL_MIN_ROWS_TBB` on numba's TBB layer, the default where the ``tbb`` wheel installs) or a D-SSIM
  over less than :data:`PARALLEL_MIN_PIXELS` pixels. The compositing kernels always run on every thread.

Measured side by side in one process (2 threads, updates of the kitchen map, benchmarks/speed/update_time.py for
whole updates), stop 39: torch's ops on one thread made 1/4- and 1/2-scale updates 20 % and 15 % faster and
full-scale (307k pixels) ones 4 % slower; at 2.8k Gaussians in view the per-Gaussian kernels and the 160x120
D-SSIM ran 3-9 % faster on one thread, at 14k even, at 60k parallel won by 5-8 %. Together: a 1/4-scale update of
the 4k-Gaussian kitchen map at 2 threads 16.9 -> 11.2 ms (it had been slower than on one thread). Stop 43, after
the compositing kernels' rework (stop 41) and with a benchmark that times consecutive updates: the kernels' limits
down from 50k rows / 150k pixels to 10k / 16k (the 160x120 D-SSIM, ~0.8 ms on one thread, now on every thread):
a 1/4-scale update with 16k Gaussians in view 15.9 -> 14.1 ms on 2 threads, 4k in view 7.8 -> 7.5; the kitchen's
default run 0.92-1.01 of the time per update (four interleaved whole-run pairs, the same map bit for bit). Limits
of 1k / 4k gained 10 % more on idle updates of the kitchen map but lost 11 % while another process kept the second
core busy (every parallel region waits for its worker's time slice), so small kernels stay on one thread. The same
bits either way (tests/core/test_threads.py).
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

PARALLEL_MIN_ROWS = 10_000  # Gaussians: compiled kernels over the rows in view (projection, culling, Adam, noise)
# the same on numba's TBB layer (eligsir_o3d/runtime/tbb.py), whose workers need no wake-up: 4k in view at 1/4
# scale, 2 threads, stop 47: 7.6-7.9 -> 6.8-7.0 ms a quiet update (500-4000 alike), 14.4-16.6 -> 14.7-16.0 beside
# a busy process
PARALLEL_MIN_ROWS_TBB = 2_000
PARALLEL_MIN_PIXELS = 16_000  # image pixels: the compiled D-SSIM
TORCH_MIN_ROWS = 50_000  # Gaussians last in view: torch's ops of an update on the caller's threads from here
TORCH_MIN_PIXELS = 150_000  # image pixels: the same


@contextmanager
def torch_threads(n: int):
    """Run the block with ``torch.set_num_threads(n)``, then restore the caller's count; ``n <= 0``: unchanged.
    Nested blocks with the same ``n`` change nothing (setting the count costs well under a microsecond)."""
    old = torch.get_num_threads()
    if n <= 0 or n == old:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def report() -> dict:
    """The threads a run had, for metrics.json: torch's count, and numba's count and threading layer once a
    compiled kernel has run (``tbb`` where the ``tbb`` wheel loaded first, eligsir_o3d/runtime/tbb.py; else ``omp``)."""
    import sys

    out = {"torch": torch.get_num_threads()}
    numba = sys.modules.get("numba")
    if numba is not None:
        out["numba"] = numba.get_num_threads()
        try:
            out["numba_layer"] = numba.threading_layer()
        except ValueError:  # no parallel kernel has run in this process
            pass
    return out
