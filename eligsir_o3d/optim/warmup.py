"""First-use costs paid ahead of a stream: one render of a one-Gaussian scene and the supervision loss
back-propagated through it (numba compilation or cache load for the ``cpu`` renderer and the CPU D-SSIM, CUDA
kernel loading for ``gsplat``), and one update of the kernel set (its select, backward and step) on a scratch
one-Gaussian map."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, GaussianMap
from ..kernels.base import StepTerms
from .losses import supervision_loss

_CAMERA = Camera(16, 16, 16.0, 16.0, 7.5, 7.5)


def warm_up(renderer, loss_cfg, device: torch.device, background: torch.Tensor, kernels=None,
            sh_degree: int = 0) -> float:
    """Render and back-propagate once on ``device`` with ``renderer`` and the loss of ``loss_cfg``, then (with
    ``kernels``, a kernel set) one update on a scratch map of ``sh_degree``; returns the seconds it took. Nothing
    outside its own tensors changes, and no random generator is drawn from."""
    t0 = time.perf_counter()
    means = torch.tensor([[0.0, 0.0, 1.0]], device=device, requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    scales, colors = torch.full((1, 3), 0.1, device=device), torch.full((1, 3), 0.5, device=device)
    opacities = torch.full((1,), 0.5, device=device)
    out = renderer.render(means, quats, scales, opacities, colors, _CAMERA, np.eye(4), background)
    loss = supervision_loss(out, torch.zeros_like(out.color), torch.ones_like(out.depth), loss_cfg)[0]
    (loss + out.alpha.sum()).backward()  # the loss's own compiled kernels (D-SSIM on the CPU) load here too
    if kernels is not None:
        _warm_kernels(kernels, renderer, loss_cfg, device, background, sh_degree)
    return time.perf_counter() - t0


def _warm_kernels(kernels, renderer, loss_cfg, device, background, sh_degree: int) -> None:
    gmap = GaussianMap(sh_degree, device)
    gmap.add(torch.tensor([[0.0, 0.0, 1.0]], device=device), torch.full((1, 3), 0.5, device=device),
             torch.full((1,), 0.1, device=device), 0.5)
    view = kernels.select(gmap, _CAMERA, np.eye(4), EPS2D)
    out = renderer.render(*view.render_args(), _CAMERA, np.eye(4), background, low_pass=EPS2D)
    color, depth = torch.zeros(16, 16, 3, device=device), torch.ones(16, 16, device=device)
    kernels.backward(out, color, depth, loss_cfg, view, StepTerms())  # no noise: no generator drawn from
    kernels.step(gmap, view, StepTerms())
