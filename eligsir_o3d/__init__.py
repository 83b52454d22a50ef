"""eligsir_o3d: budget-aware online RGB-D Gaussian-splatting mapping (EliGSiR) as an Open3D plugin."""

import os

# torch and the numba rasteriser share one OpenMP runtime; its default spin-waiting starves the main thread on a
# busy machine (measured: up to 16x slower renders at load 3-10 on 2 cores). Passive waiting costs little when
# idle. It only takes effect if set before torch is first imported; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from . import tbb_runtime  # noqa: E402
from ._open3d_check import import_open3d  # noqa: E402

tbb_runtime.preload()  # before Open3D loads its older TBB (eligsir_o3d/tbb_runtime.py): numba's kernels then run on TBB
import_open3d()  # a missing system library (libusb, libGL, ...) fails here with one line naming the package

from .core.camera import Camera  # noqa: E402
from .config import Config
from .core.frame import Frame, FrameError
from .core.gaussians import GaussianMap
from .reconstructor import Reconstructor
from .render import RenderOutput, get_renderer

from ._version import __version__  # noqa: E402

__all__ = ["Camera", "Config", "Frame", "FrameError", "GaussianMap", "Reconstructor", "RenderOutput", "get_renderer",
           "__version__"]
