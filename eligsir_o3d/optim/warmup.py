"""First-use costs paid ahead of a stream: one render of a one-Gaussian scene and the supervision loss
back-propagated through it (numba compilation or cache load for the ``cpu`` renderer and the CPU D-SSIM, CUDA
kernel loading for ``gsplat``)."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..core.camera import Camera
from .losses import supervision_loss


def warm_up(renderer, loss_cfg, device: torch.device, background: torch.Tensor) -> float:
    """Render and back-propagate once on ``device`` with ``renderer`` and the loss of ``loss_cfg``; returns the
    seconds it took. Nothing outside its own tensors changes."""
    t0 = time.perf_counter()
    means = torch.tensor([[0.0, 0.0, 1.0]], device=device, requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    scales, colors = torch.full((1, 3), 0.1, device=device), torch.full((1, 3), 0.5, device=device)
    opacities = torch.full((1,), 0.5, device=device)
    out = renderer.render(means, quats, scales, opacities, colors, Camera(16, 16, 16.0, 16.0, 7.5, 7.5), np.eye(4),
                          background)
    loss = supervision_loss(out, torch.zeros_like(out.color), torch.ones_like(out.depth), loss_cfg)[0]
    (loss + out.alpha.sum()).backward()  # the loss's own compiled kernels (D-SSIM on the CPU) load here too
    return time.perf_counter() - t0
