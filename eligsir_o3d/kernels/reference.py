"""The ``torch`` kernel set: every stage in composed torch operators, on any device and dtype.

The reference the fused sets are tested against, and what runs where no compiled set applies (a float64 map, a
device without Triton). Autograd carries the gradient through the activations and the regulariser; Adam and the
position noise are torch's formulas on the view's rows.
"""

from __future__ import annotations

import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, PARAM_NAMES
from ..render.projection import quat_to_rotmat
from .base import KernelSet, RowView, StepTerms, adam_factors, moments
from .cpu import regulariser
from ..render.culling import in_view_torch


@torch.no_grad()
def noise_torch(gmap, rows: torch.Tensor | None, scaler: float, generator) -> None:
    """MCMC's covariance-shaped, opacity-gated position noise on ``rows`` (None: all) in torch operators."""
    p = gmap.params
    idx = torch.arange(len(gmap), device=gmap.device) if rows is None else rows
    if idx.numel() == 0:
        return
    quats, scales = p["quats"].detach()[idx], torch.exp(p["scales"].detach()[idx])
    o = torch.sigmoid(p["opacities"].detach()[idx])
    z = torch.randn(idx.numel(), 3, generator=generator, device=o.device, dtype=o.dtype)
    gate = torch.sigmoid(100.0 * ((1.0 - o) - 0.995))
    M = quat_to_rotmat(quats) * scales[:, None, :]
    p["means"].data[idx] += torch.einsum("nij,nj->ni", M @ M.transpose(1, 2), z) * (gate * scaler)[:, None]
    gmap.touched(rows)


class TorchKernels(KernelSet):
    """Composed torch operators on any device (see the module docstring)."""

    name = "torch"

    def select(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D, *, cull: bool = True,
               grad: bool = True, capacity: int = 0) -> RowView:
        p = gmap.params
        if cull:
            idx = in_view_torch(p["means"], p["scales"], camera, T_world_cam, low_pass)
        else:
            idx = torch.arange(len(gmap), device=gmap.device)
        leaves = {n: p[n].detach()[idx].requires_grad_(grad) for n in PARAM_NAMES}
        return RowView(gmap, idx, leaves, activated=False)

    def backward(self, out, color, depth, loss_cfg, view: RowView, terms: StepTerms) -> torch.Tensor:
        from ..optim.losses import torch_loss

        loss, error = torch_loss(out, color, depth, loss_cfg)
        if (reg := regulariser(view, terms)) is not None:
            loss = loss + reg
        if loss.requires_grad:
            loss.backward()
        return error

    @torch.no_grad()
    def step(self, gmap, view: RowView, terms: StepTerms) -> None:
        if len(gmap) != view.n_map:
            raise RuntimeError(f"the map changed size ({view.n_map} -> {len(gmap)}) between render and step")
        idx = view.idx
        for name in PARAM_NAMES:
            p, g = gmap.params[name], view.leaves[name].grad
            if g is None or p.numel() == 0:
                continue
            m, v = moments(gmap, name)
            a, b, w, b2, w2, eps = adam_factors(gmap, name)
            mi = m[idx] + w * (g - m[idx])
            vi = v[idx] * b2 + w2 * g * g
            m[idx], v[idx] = mi, vi
            p.data[idx] = p.data[idx] + a * (mi / (torch.sqrt(vi) / b + eps))
        gmap.touched(idx)
        if terms.noise_scaler > 0:
            self.noise(gmap, idx, terms.noise_scaler, terms.generator)

    def noise(self, gmap, rows, scaler: float, generator) -> None:
        noise_torch(gmap, rows, scaler, generator)
