"""eligsir_o3d: budget-aware online RGB-D Gaussian-splatting mapping (EliGSiR) as an Open3D plugin."""

from .camera import Camera
from .config import Config
from .frame import Frame, FrameError
from .gaussians import GaussianMap
from .reconstructor import Reconstructor
from .render import RenderOutput, get_renderer

__version__ = "0.1.0"

__all__ = ["Camera", "Config", "Frame", "FrameError", "GaussianMap", "Reconstructor", "RenderOutput", "get_renderer",
           "__version__"]
