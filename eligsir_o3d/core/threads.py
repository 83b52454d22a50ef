"""Threads that pay on the CPU. The package waits passively for OpenMP work (``eligsir_o3d/__init__.py``: spinning
workers starve the main thread of a busy machine), so every parallel region wakes sleeping workers: ~55-60 us per
region on the 2-core machines measured (a 2-thread region of trivial work; 1.5 us on one thread). A parallel step
shorter than ~0.2 ms loses more to the wake-up than a second thread saves, and a 1/4-scale mapping update is made
of dozens of such steps: torch's operations on a few thousand rows or a 160x120 image, and compiled kernels over
the Gaussians in view.

- :func:`torch_threads`: torch's thread count for a block (``optim.torch_threads``: 1 by default), used by the
  :class:`~eligsir_o3d.Reconstructor` for frames' admission and growth and for updates on images below
  :data:`PARALLEL_MIN_PIXELS` with fewer than :data:`PARALLEL_MIN_ROWS` Gaussians in view (the last update's);
  larger ones keep the caller's count (77k Gaussians in view at 1/4 scale: 0.96 of the time on 2 threads, 16k even);
- :func:`.jit.threads_for`: one numba thread for a kernel over less than :data:`PARALLEL_MIN_ROWS` Gaussians or a
  D-SSIM over less than :data:`PARALLEL_MIN_PIXELS` pixels. The compositing kernels always run on every thread.

Measured side by side in one process (2 threads, updates of the kitchen map, benchmarks/speed/update_time.py for
whole updates): torch's ops on one thread made 1/4- and 1/2-scale updates 20 % and 15 % faster and full-scale
(307k pixels) ones 4 % slower; at 2.8k Gaussians in view the per-Gaussian kernels and the 160x120 D-SSIM ran 3-9 %
faster on one thread, at 14k even, at 60k parallel won by 5-8 %; D-SSIM at 320x240 even, at 640x480 parallel won
by 10 %. Together: a 1/4-scale update of the 4k-Gaussian kitchen map at 2 threads 16.9 -> 11.2 ms (it had been
slower than on one thread). The same bits either way (tests/core/test_threads.py).
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

PARALLEL_MIN_ROWS = 50_000  # Gaussians: projection, culling, Adam over the rows in view
PARALLEL_MIN_PIXELS = 150_000  # image pixels: D-SSIM, torch's ops of an update


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
