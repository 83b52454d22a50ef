"""Losses of one supervision update: photometric L1 + D-SSIM and depth L1 (3DGS / SplaTAM style)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from pytorch_msssim import ssim as _ssim

from .render import RenderOutput


@dataclass
class LossConfig:
    lambda_dssim: float = 0.2  # weight of D-SSIM against L1 in the photometric term (3DGS uses 0.2)
    lambda_depth: float = 0.5  # weight of the depth L1 (metres) term
    depth_alpha_min: float = 0.5  # depth supervises only pixels the map already covers (growth handles the rest)


def dssim(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """1 - SSIM as in 3DGS: 11x11 Gaussian window (shrunk for tiny images); pred, ref [H, W, 3]."""
    win = min(11, (min(pred.shape[0], pred.shape[1]) // 2) * 2 - 1)
    if win < 3:
        return torch.zeros((), device=pred.device)
    x = pred.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None]
    return 1.0 - _ssim(x, y, data_range=1.0, size_average=True, win_size=win)


def supervision_loss(out: RenderOutput, color: torch.Tensor, depth: torch.Tensor, cfg: LossConfig):
    """Loss of one training render against its view (color [h, w, 3], depth [h, w] metres, 0 = missing).

    Returns (loss, error [h, w]): the detached per-pixel photometric error that Map-Guided View Scheduling
    accumulates into microcells, so the spatial signal costs no extra render.
    """
    abs_err = (out.color - color).abs()  # [h, w, 3]
    l1 = abs_err.mean()
    loss = (1.0 - cfg.lambda_dssim) * l1
    if cfg.lambda_dssim > 0:
        loss = loss + cfg.lambda_dssim * dssim(out.color, color)
    if cfg.lambda_depth > 0:
        valid = (depth > 0) & (out.alpha.detach() > cfg.depth_alpha_min)
        if valid.any():
            loss = loss + cfg.lambda_depth * (out.depth[valid] - depth[valid]).abs().mean()
    return loss, abs_err.detach().mean(-1)
