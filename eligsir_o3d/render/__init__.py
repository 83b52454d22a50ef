"""Renderer backends behind one dispatch point, :func:`get_renderer`.

- ``torch``: pure PyTorch reference (any device, autograd) - the oracle the others are tested against.
- ``cpu``: compiled CPU tile rasteriser (forward and backward); the default without CUDA.
- ``gsplat``: ``gsplat.rasterization`` on CUDA; the default with CUDA when gsplat's compiled extension loads
  (:mod:`.availability`).
"""

from __future__ import annotations

import importlib.util
import logging

import torch

from .availability import GsplatStatus, GsplatUnavailable, gsplat_status, load_gsplat_extension
from .base import RenderOutput, TileRenderer, render_map
from .torch_backend import TorchRenderer

__all__ = ["RenderOutput", "TileRenderer", "TorchRenderer", "available_backends", "get_renderer", "render_map"]

log = logging.getLogger("eligsir_o3d")


def _cpu_backend_available() -> bool:
    return importlib.util.find_spec("eligsir_o3d.render.cpu_backend") is not None and \
        importlib.util.find_spec("numba") is not None


def _gsplat_available(device: torch.device) -> bool:
    return gsplat_status(device).usable


def available_backends(device: str | torch.device = "cpu") -> list[str]:
    device = torch.device(device)
    names = ["torch"]
    if device.type == "cpu" and _cpu_backend_available():
        names.append("cpu")
    if _gsplat_available(device):
        names.append("gsplat")
    return names


def resolve_backend(name: str, device: str | torch.device) -> str:
    """``auto`` -> gsplat on CUDA when its extension really loads, else cpu on the CPU, else torch.

    When gsplat would first have to JIT-compile its extension, ``auto`` compiles it here (logged), so that a failed
    build still falls back. A fallback is logged in one line that says why gsplat was not taken.
    """
    device = torch.device(device)
    if name != "auto":
        return name
    status = gsplat_status(device)
    if status.usable and status.compile_pending:
        try:
            load_gsplat_extension()
        except GsplatUnavailable as err:
            status = GsplatStatus(False, err.reason)
    if status.usable:
        return "gsplat"
    fallback = "cpu" if device.type == "cpu" and _cpu_backend_available() else "torch"
    level = logging.WARNING if device.type == "cuda" else logging.INFO
    log.log(level, "renderer auto -> %s, not gsplat: %s", fallback, status.reason)
    return fallback


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
        from .gsplat_backend import GsplatRenderer  # checks gsplat_status and says what to install
        return GsplatRenderer(device)
    raise ValueError(f"unknown renderer {name!r}; choose from auto, torch, cpu, gsplat")
