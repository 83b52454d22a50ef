"""Torch's CPU threads while the mapper works: a mapping update's torch operations are small (a few thousand rows,
a 160x120 image), too small to gain from a second thread, yet each parallel torch operation wakes torch's OpenMP
workers, and the package's passive OpenMP waiting (``eligsir_o3d/__init__.py``) makes every wake-up cost
~50-100 us on the 2-core machines measured (a 2-thread parallel region of trivial work: 55-62 us passive, 1.5 us on
one thread). The compiled CPU kernels (rasteriser, D-SSIM, Adam) run on numba's own threads and are not affected.
:func:`torch_threads` sets torch's thread count for the duration of a block and restores it (``optim.torch_threads``
in :meth:`~eligsir_o3d.Reconstructor.integrate` and :meth:`~eligsir_o3d.Reconstructor.optimize`)."""

from __future__ import annotations

from contextlib import contextmanager

import torch


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
