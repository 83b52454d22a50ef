"""A Reconstructor rebuilt from a decoded checkpoint (``io.checkpoint.read_checkpoint``'s dict): the config, camera
and device it was saved with, then its :class:`~.state.MapperState` restored."""

from __future__ import annotations

from typing import Callable

import torch

from ..config import Config
from ..core.camera import Camera
from ..io.checkpoint import CheckpointError


def restore(cls, ck: dict, device: str | None = None, *, pose_source=None, setup: Callable | None = None):
    """A ``cls`` (Reconstructor) built from ``ck`` on ``device`` (default: where it was saved; the renderer is
    re-chosen when the device type changes); ``setup(rec)`` runs before the state is restored (for policies
    replaced after construction). Raises :class:`CheckpointError` naming the file."""
    path = ck.get("path", "checkpoint")
    if ck.get("unresolved_views"):
        raise CheckpointError(f"{path}: {ck['unresolved_views']} views were saved as references to a sequence; "
                              f"pass sequence= (the one given when saving) to load it")
    cfg = Config.from_dict(ck["config"])
    saved_dev = torch.device(ck["device"])
    dev = torch.device(device) if device is not None else saved_dev
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CheckpointError(f"{path}: saved on {saved_dev}, but CUDA is not available here; "
                              f"pass device='cpu' to load it on the CPU")
    if dev.type != saved_dev.type:
        cfg.renderer = "auto"
    rec = cls(Camera(**ck["camera"]), str(dev), cfg, pose_source=pose_source, offline_frames=ck.get("offline_frames"))
    if setup is not None:
        setup(rec)
    try:
        rec.state.load_state_dict(ck)
    except ValueError as e:
        raise CheckpointError(f"{path}: {e}") from None
    return rec
