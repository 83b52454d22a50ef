"""eligsir_o3d: budget-aware online RGB-D Gaussian-splatting mapping (EliGSiR) as an Open3D plugin.

``import eligsir_o3d`` imports only this file: each public name below loads its module on first use, after the
process-level set-up (:func:`eligsir_o3d.runtime.prepare`).
"""

from __future__ import annotations

import importlib

from ._version import __version__

_PUBLIC = {  # name -> the module that defines it
    "Camera": "core.camera", "Config": "config", "Frame": "core.frame", "FrameError": "core.frame",
    "GaussianMap": "core.gaussians", "Reconstructor": "mapper", "RenderOutput": "render",
    "get_renderer": "render",
}

__all__ = ["Camera", "Config", "Frame", "FrameError", "GaussianMap", "Reconstructor", "RenderOutput", "get_renderer",
           "__version__"]


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from .runtime import prepare

    prepare()
    value = getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
