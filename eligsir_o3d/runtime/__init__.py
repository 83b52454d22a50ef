"""Process-level set-up, done once on first use and never by ``import eligsir_o3d``.

- :func:`prepare`: what the process needs before the package loads Open3D and torch: OpenMP's passive waiting
  (spinning workers starve the main thread of a busy machine; it takes effect only before torch is first imported,
  and a user's own ``OMP_WAIT_POLICY`` wins), the ``tbb`` wheel's library loaded before Open3D's older copy
  (:mod:`.tbb`: numba's kernels then run on TBB), and Open3D imported with a missing system library named in one
  line (:mod:`.open3d_check`). The package's public names (``eligsir_o3d.Reconstructor``, ...) and the ``eligsir``
  command call it before their first import; a script that imports Open3D or torch first gets the defaults of
  those libraries (numba then runs on OpenMP), with the same results.
- :mod:`.jit`: the numba decorators of every compiled kernel; importing it calls :func:`prepare` and picks numba's
  threading layer before the first kernel compiles.
- :mod:`.threads`: when torch and numba work on one thread or on all of them.

This package imports neither torch, numba nor Open3D until one of these is used.
"""

from __future__ import annotations

import os
import sys

_prepared = False


def prepare() -> None:
    """The process-level set-up above, once per process (later calls return at once)."""
    global _prepared
    if _prepared:
        return
    if "torch" not in sys.modules:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from . import tbb
    from .open3d_check import import_open3d

    tbb.preload()
    import_open3d()  # a missing system library (libusb, libGL, ...) fails here with one line naming the package
    _prepared = True
