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
- :func:`.jit.rows_threads`: a per-Gaussian kernel runs on every numba thread over :data:`PARALLEL_MIN_ROWS`
  Gaussians or more (:data:`PARALLEL_MIN_ROWS_TBB` on numba's TBB layer, the default where the ``tbb`` wheel
  installs) and on one below :data:`PARALLEL_FLOOR_ROWS`; in between, where a second thread pays on an idle
  machine and loses beside a busy process, the way measured faster during the run (:mod:`.row_threads`);
- :func:`.jit.threads_for`: one numba thread for a D-SSIM over less than :data:`PARALLEL_MIN_PIXELS` pixels. The
  compositing kernels always run on every thread.

The limits were measured side by side in one process (2 threads, updates of the kitchen map,
``benchmarks/speed/update_time.py`` for whole updates; lab: thread-limits): small work on one thread is faster on an
idle machine and much faster beside a busy process, large work still gains from every thread. The same bits either
way (tests/core/test_threads.py).
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

PARALLEL_MIN_ROWS = 10_000  # Gaussians: compiled kernels over the rows in view (projection, culling, Adam, noise)
# the same on numba's TBB layer (eligsir_o3d/runtime/tbb.py), whose workers need no wake-up (lab: thread-limits)
PARALLEL_MIN_ROWS_TBB = 8_000
PARALLEL_FLOOR_ROWS = 1_000  # Gaussians: below this, a per-Gaussian kernel runs on one thread (no choice measured)
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
    jit = sys.modules.get("eligsir_o3d.runtime.jit")
    if jit is not None:
        out["row_kernels"] = jit.ROW_THREADS.report()  # calls between the limits on one thread and on all
    return out

