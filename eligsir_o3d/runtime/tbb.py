"""oneTBB for numba's threading layer: load the ``tbb`` wheel's library before Open3D loads its own.

Why numba should run its kernels on TBB here, not on OpenMP: the package makes OpenMP wait passively
(:func:`eligsir_o3d.runtime.prepare`: spinning workers starve the main thread of a busy machine), so every parallel
region of an OpenMP kernel wakes a sleeping worker, ~55-60 us on the 2-core machines measured, and a 1/4-scale
mapping update runs ~30 such regions. TBB's idle workers spin a little, yielding, before they sleep: the next
region finds its worker awake, and on a loaded machine the yielding spin gives its time slice away. Measured with
``benchmarks/speed/update_time.py`` (lab: tbb-layer): faster on a quiet machine, the same as OpenMP beside busy
processes.

Two obstacles, both handled here with nothing but ``ctypes`` (``import eligsir_o3d`` stays free of numba):

- pip installs the wheel's ``libtbb.so.12`` into the environment's ``lib/``, off the dynamic loader's path, so
  numba's TBB layer cannot find it;
- Open3D's Linux wheel bundles an older ``libtbb.so.12`` (interface 12050; numba needs >= 12060). Whichever
  library of that name loads first serves the whole process, Open3D included (oneTBB keeps its ABI within .12).

So :func:`preload` runs before the package imports Open3D (:func:`eligsir_o3d.runtime.prepare`). If Open3D came first (a script that imports open3d before
eligsir_o3d), its TBB serves and :func:`usable` is False: numba then runs on OpenMP, as before, with no warning.
"""

from __future__ import annotations

import ctypes
import site
import sys
from pathlib import Path

LIBRARY = "libtbb.so.12"  # oneTBB 2021+, the ABI numba's TBB layer links
MIN_INTERFACE = 12060  # numba's own floor (numba/np/ufunc/parallel.py)


def _candidates() -> list[str]:
    dirs = [Path(sys.prefix) / "lib", Path(sys.base_prefix) / "lib", Path(site.getuserbase()) / "lib"]
    return [str(d / LIBRARY) for d in dirs if (d / LIBRARY).is_file()]


def preload() -> bool:
    """Load the environment's ``libtbb.so.12`` process-wide (Linux; elsewhere nothing). True when one loaded."""
    if not sys.platform.startswith("linux"):
        return False
    for path in _candidates():
        try:
            ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
            return True
        except OSError:
            continue
    return False


def interface_version() -> int | None:
    """The interface version of the ``libtbb.so.12`` this process resolves (the first loaded), None without one."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return int(ctypes.CDLL(LIBRARY).TBB_runtime_interface_version())
    except (OSError, AttributeError):
        return None


def usable() -> bool:
    """Whether numba's TBB layer would accept the TBB this process has."""
    v = interface_version()
    return v is not None and v >= MIN_INTERFACE
