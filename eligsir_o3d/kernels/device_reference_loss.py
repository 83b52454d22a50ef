"""The supervision loss with its gradient in plain torch, on any device and without a host sync: the reference of
:mod:`.triton_loss` and its fallback where Triton is absent.

:func:`fused_loss` is :func:`.optim.losses.supervision_loss` of a render's accumulations (the loss of
``optim.losses._FusedLossCPU``): the finished colour x = rgb sums + (1 - alpha) background, the photometric L1
(weight (1 - lambda_dssim) / 3HW), D-SSIM over the 'valid' Gaussian window (11 taps, sigma 1.5; fewer on a small
image, none below 3), and the depth L1 over the valid pixels (reference depth > 0, alpha > alpha_min; the rendered
depth is depth sum / alpha where alpha > 1e-4, else 0) with weight lambda_depth / n_valid (0 without valid
pixels; n_valid stays on the device). The loss is a sum of means, so its gradient with respect to the
accumulations is written out here, not taped: D-SSIM's through the transposed window (see
:mod:`.optim.dssim_kernels` for the formulas).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

DEPTH_ALPHA_EPS = 1e-4  # the rendered depth is depth sum / alpha above this alpha, else 0
C1, C2 = 0.01 ** 2, 0.03 ** 2
SIGMA = 1.5


def dssim_window(h: int, w: int, win: int = 11) -> int:
    """The taps of D-SSIM's window on an h x w image: ``win``, fewer (odd) on a small image; below 3, no D-SSIM."""
    return min(win, (min(h, w) // 2) * 2 - 1)


@lru_cache(maxsize=16)
def window_taps(win: int, sigma: float = SIGMA) -> tuple[float, ...]:
    """The normalised 1-D Gaussian window (``win`` taps, ``sigma`` px) as host floats."""
    t = [math.exp(-((k - (win - 1) / 2) ** 2) / (2 * sigma * sigma)) for k in range(win)]
    return tuple(v / sum(t) for v in t)


@lru_cache(maxsize=32)
def _band(n: int, win: int, device: str) -> torch.Tensor:
    """[n, n - win + 1] float32: ``a @ M`` is the 'valid' window filter along a's last axis (built once per shape
    and device, on the device)."""
    taps = torch.tensor(window_taps(win), dtype=torch.float32)
    k = torch.arange(n)[:, None] - torch.arange(n - win + 1)[None]
    return torch.where((k >= 0) & (k < win), taps[k.clamp(0, win - 1)], 0.0).to(device)


def dssim_and_grad(x: torch.Tensor, y: torch.Tensor, win: int):
    """(D-SSIM [] , d D-SSIM / dx [3, H, W]) of x, y [3, H, W] float32 over the 'valid' ``win``-tap window."""
    h, w = x.shape[1], x.shape[2]
    bh, bw = _band(h, win, str(x.device)), _band(w, win, str(x.device))
    mu_x, mu_y, exx, eyy, exy = (bh.T @ (torch.cat([x, y, x * x, y * y, x * y], 0) @ bw)).split(3, 0)
    a1, b1 = 2 * mu_x * mu_y + C1, mu_x * mu_x + mu_y * mu_y + C1
    a2, b2 = 2 * (exy - mu_x * mu_y) + C2, (exx - mu_x * mu_x) + (eyy - mu_y * mu_y) + C2
    s = (a1 * a2) / (b1 * b2)
    f = s * (-1.0 / s.numel())  # dL/dS = -1/N times S
    d = torch.cat([f * 2 * (mu_y / a1 - mu_x / b1 - mu_y / a2 + mu_x / b2), -f / b2, 2 * f / a2], 0)
    t = bh @ (d @ bw.T)  # [9, H, W]: the transposed window
    return 1.0 - s.mean(), t[0:3] + 2 * x * t[3:6] + y * t[6:9]


def fused_loss(acc, alpha, background, color, depth, lambda_dssim: float, lambda_depth: float,
               alpha_min: float):
    """(loss [], error [H, W], grad_acc [H, W, 4], grad_alpha [H, W]) from the accumulations acc [H, W, 4] (rgb,
    depth sums without background), alpha [H, W], background [3] or None, against color [H, W, 3] and depth
    [H, W] (metres, 0 = missing): see the module docstring. The gradients are d loss / d acc, d loss / d alpha."""
    acc, alpha = acc.detach(), alpha.detach()
    h, w = alpha.shape
    om = (1.0 - alpha)[..., None]
    x = acc[..., :3] + om * background.reshape(3) if background is not None else acc[..., :3]
    ref = color.to(torch.float32)
    diff = x - ref
    error = diff.abs().mean(-1)
    w_l1 = (1.0 - lambda_dssim) / (3 * h * w)
    loss = w_l1 * diff.abs().sum()
    g_rgb = w_l1 * torch.sign(diff)
    win = dssim_window(h, w)
    if lambda_dssim > 0 and win >= 3:
        d_val, d_grad = dssim_and_grad(x.permute(2, 0, 1).contiguous(), ref.permute(2, 0, 1).contiguous(), win)
        loss = loss + lambda_dssim * d_val
        g_rgb = g_rgb + lambda_dssim * d_grad.permute(1, 2, 0)
    g_acc_d = torch.zeros_like(alpha)
    g_alpha = -(g_rgb * background.reshape(3)).sum(-1) if background is not None else torch.zeros_like(alpha)
    if lambda_depth > 0:
        ref_d = depth.to(torch.float32)
        drawn = alpha > DEPTH_ALPHA_EPS
        a_safe = torch.where(drawn, alpha, 1.0)
        pred = torch.where(drawn, acc[..., 3] / a_safe, 0.0)
        valid = (ref_d > 0) & (alpha > alpha_min)
        n_valid = valid.sum()
        w_depth = torch.where(n_valid > 0, lambda_depth / n_valid.clamp_min(1).to(torch.float32), 0.0)
        dd = torch.where(valid, pred - ref_d, 0.0)
        loss = loss + w_depth * dd.abs().sum()
        gp = torch.where(valid & drawn, w_depth * torch.sign(dd), 0.0)  # d loss / d rendered depth
        g_acc_d = gp / a_safe
        g_alpha = g_alpha - gp * acc[..., 3] / (a_safe * a_safe)
    grad_acc = torch.cat([g_rgb, g_acc_d[..., None]], -1)
    return loss, error, grad_acc, g_alpha
