"""Renderer backends behind one dispatch point, :func:`get_renderer`.

- ``torch``: pure PyTorch reference (any device, autograd) - the oracle the others are tested against.
- ``cpu``: compiled CPU tile rasteriser (forward and backward); the default without CUDA.
- ``gsplat``: ``gsplat.rasterization`` on CUDA; the default with CUDA and gsplat installed.
"""

from __future__ import annotations

import importlib.util

import torch

from .base import RenderOutput, TileRenderer
from .torch_backend import TorchRenderer

__all__ = ["RenderOutput", "TileRenderer", "TorchRenderer", "available_backends", "get_renderer"]


def _cpu_backend_available() -> bool:
    return importlib.util.find_spec("eligsir_o3d.render.cpu_backend") is not None and \
        importlib.util.find_spec("numba") is not None


def _gsplat_available(device: torch.device) -> bool:
    return device.type == "cuda" and torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def available_backends(device: str | torch.device = "cpu") -> list[str]:
    device = torch.device(device)
    names = ["torch"]
    if device.type == "cpu" and _cpu_backend_available():
        names.append("cpu")
    if _gsplat_available(device):
        names.append("gsplat")
    return names


def resolve_backend(name: str, device: str | torch.device) -> str:
    """``auto`` -> gsplat on CUDA (when installed), else cpu on the CPU, else torch."""
    device = torch.device(device)
    if name != "auto":
        return name
    if _gsplat_available(device):
        return "gsplat"
    if device.type == "cpu" and _cpu_backend_available():
        return "cpu"
    return "torch"


def get_renderer(name: str = "auto", device: str | torch.device = "cpu"):
    """Renderer instance by name (``auto``, ``torch``, ``cpu``, ``gsplat``) for ``device``."""
    device = torch.device(device)
    name = resolve_backend(name, device)
    if name == "torch":
        return TorchRenderer(device)
    if name == "cpu":
        if device.type != "cpu":
            raise ValueError(f"the 'cpu' renderer runs on the CPU only, not on {device}")
        from .cpu_backend import CpuRenderer
        return CpuRenderer(device)
    if name == "gsplat":
        if not _gsplat_available(device):
            raise RuntimeError("the 'gsplat' renderer needs a CUDA device and gsplat "
                               "(pip install 'eligsir-o3d[cuda]'); use --renderer cpu or torch")
        from .gsplat_backend import GsplatRenderer
        return GsplatRenderer(device)
    raise ValueError(f"unknown renderer {name!r}; choose from auto, torch, cpu, gsplat")
