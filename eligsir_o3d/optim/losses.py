"""Losses of one supervision update: photometric L1 + D-SSIM and depth L1 (3DGS / SplaTAM style)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from ..render import RenderOutput


@dataclass
class LossConfig:
    lambda_dssim: float = 0.2
    """Weight of D-SSIM against L1 in the photometric term."""
    lambda_depth: float = 0.5
    """Weight of the depth L1 term (metres)."""
    depth_alpha_min: float = 0.5
    """Depth supervises only pixels whose rendered opacity reaches this (growth handles the rest)."""


@lru_cache(maxsize=32)
def _blur_matrix(n: int, win: int, sigma: float, device: str) -> torch.Tensor:
    """[n, n - win + 1] banded matrix: ``x @ M`` is a 'valid' 1D Gaussian filter along x's last axis."""
    t = torch.arange(win, dtype=torch.float32) - (win - 1) / 2
    g = torch.exp(-(t * t) / (2 * sigma * sigma))
    g = g / g.sum()
    m = torch.zeros(n, n - win + 1)
    cols = torch.arange(n - win + 1)
    for k in range(win):
        m[cols + k, cols] = g[k]
    return m.to(device)


@lru_cache(maxsize=8)
def _window(win: int, sigma: float) -> np.ndarray:
    t = np.arange(win, dtype=np.float64) - (win - 1) / 2
    g = np.exp(-(t * t) / (2 * sigma * sigma))
    return (g / g.sum()).astype(np.float32)


class _DssimCPU(torch.autograd.Function):
    """D-SSIM by the numba kernel (:mod:`._dssim_kernels`): value and gradient in one pass."""

    @staticmethod
    def forward(ctx, pred, ref, win: int, sigma: float):
        from ..runtime.jit import pixels_threads
        from .dssim_kernels import dssim_value_and_grad

        x = np.ascontiguousarray(pred.detach().permute(2, 0, 1).numpy())
        y = np.ascontiguousarray(ref.detach().permute(2, 0, 1).to(torch.float32).numpy())
        grad = np.empty_like(x)
        with pixels_threads(x.shape[1] * x.shape[2]):
            value = dssim_value_and_grad(x, y, _window(win, sigma), grad)
        ctx.save_for_backward(torch.from_numpy(grad).permute(1, 2, 0))
        return torch.tensor(value, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        (grad,) = ctx.saved_tensors
        return grad_out * grad, None, None, None


def _dssim_window(h: int, w: int, win: int = 11) -> int:
    """The window D-SSIM uses on an h x w image: ``win`` taps, fewer (odd) on an image too small for it; below 3
    D-SSIM is 0."""
    return min(win, (min(h, w) // 2) * 2 - 1)


def dssim(pred: torch.Tensor, ref: torch.Tensor, win: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """1 - SSIM as in 3DGS (11x11 Gaussian window, sigma 1.5, no padding); pred, ref [H, W, 3] in [0, 1].

    Same value as ``pytorch_msssim.ssim`` (tested). On the CPU in float32 a numba kernel computes value and gradient
    in one pass (5-25x faster than the torch formulation, :func:`dssim_torch`, which runs everywhere else).
    """
    win = _dssim_window(pred.shape[0], pred.shape[1], win)
    if win < 3:
        return torch.zeros((), device=pred.device)
    if pred.device.type == "cpu" and pred.dtype == torch.float32:
        return _DssimCPU.apply(pred, ref, win, sigma)
    return dssim_torch(pred, ref, win, sigma)


def dssim_torch(pred: torch.Tensor, ref: torch.Tensor, win: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """The torch formulation of :func:`dssim` (any device and dtype): the separable Gaussian filter of the five
    local moments as two banded matrix products (on the CPU ~5x faster than a grouped conv2d at 160x120)."""
    h, w = pred.shape[0], pred.shape[1]
    win = _dssim_window(h, w, win)
    if win < 3:
        return torch.zeros((), device=pred.device)
    x, y = pred.permute(2, 0, 1), ref.permute(2, 0, 1)  # [3, H, W]
    maps = torch.cat([x, y, x * x, y * y, x * y], 0)  # [15, H, W]
    bw = _blur_matrix(w, win, sigma, str(pred.device)).to(pred.dtype)
    bh = _blur_matrix(h, win, sigma, str(pred.device)).to(pred.dtype)
    mu_x, mu_y, xx, yy, xy = (bh.T @ (maps @ bw)).split(3, 0)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    sxx, syy, sxy = xx - mu_x * mu_x, yy - mu_y * mu_y, xy - mu_x * mu_y
    cs = (2 * sxy + c2) / (sxx + syy + c2)
    ssim_map = ((2 * mu_x * mu_y + c1) / (mu_x * mu_x + mu_y * mu_y + c1)) * cs
    return 1.0 - ssim_map.mean()


@lru_cache(maxsize=1)
def _compiled() -> tuple:
    """(runtime.jit, the D-SSIM kernels, the fused loss's kernels), imported (numba with them) on first use."""
    from ..runtime import jit
    from . import dssim_kernels, loss_kernels

    return jit, dssim_kernels, loss_kernels


def _host32(t: torch.Tensor) -> np.ndarray:
    """``t`` as a contiguous float32 numpy array (no operator where it already is one)."""
    t = t.detach()
    if t.dtype != torch.float32:
        t = t.to(torch.float32)
    return (t if t.is_contiguous() else t.contiguous()).numpy()


def fused_loss_cpu(acc, alpha, background, color, depth, cfg: LossConfig):
    """:func:`supervision_loss` from a ``cpu`` render's accumulations (acc [H, W, 4], alpha [H, W], the background
    or None) in compiled passes (:mod:`.loss_kernels` around the D-SSIM kernel), without autograd: (value, a host
    float; error [H, W]; the loss's gradients with respect to acc and alpha)."""
    jit, dssim_kernels, loss_kernels = _compiled()
    h, w = alpha.shape
    f32 = np.float32
    a_np, acc_np, ref_depth = _host32(alpha), _host32(acc), _host32(depth)
    has_bg = background is not None
    bg = _host32(background.reshape(3)) if has_bg else np.zeros(3, f32)
    x, y = np.empty((3, h, w), f32), np.empty((3, h, w), f32)
    error, rows = np.empty((h, w), f32), np.empty((h, 3), np.float64)
    alpha_min = f32(cfg.depth_alpha_min)
    win = _dssim_window(h, w)
    use_dssim = cfg.lambda_dssim > 0 and win >= 3
    grad_acc, grad_alpha = np.empty((h, w, 4), f32), np.empty((h, w), f32)
    with jit.pixels_threads(h * w):
        loss_kernels.loss_terms(acc_np, a_np, bg, has_bg, _host32(color), ref_depth, alpha_min, x, y, error, rows)
        l1_sum, depth_sum, n_valid = rows.sum(0)
        w_l1 = (1.0 - cfg.lambda_dssim) / (3 * h * w)
        value = w_l1 * l1_sum
        d_grad = np.empty_like(x)  # D-SSIM's gradient; not read when D-SSIM is off (its weight 0 below)
        if use_dssim:
            value += cfg.lambda_dssim * dssim_kernels.dssim_value_and_grad(x, y, _window(win, 1.5), d_grad)
        w_depth = 0.0
        if cfg.lambda_depth > 0 and n_valid > 0:
            w_depth = cfg.lambda_depth / n_valid
            value += w_depth * depth_sum
        loss_kernels.loss_grad(acc_np, a_np, bg, has_bg, x, y, ref_depth, alpha_min, f32(w_l1),
                               f32(cfg.lambda_dssim if use_dssim else 0.0), d_grad, f32(w_depth), grad_acc, grad_alpha)
    return value, torch.from_numpy(error), torch.from_numpy(grad_acc), torch.from_numpy(grad_alpha)


class _FusedLossCPU(torch.autograd.Function):
    """:func:`fused_loss_cpu` as an autograd function: its backward scales the stored gradient."""

    @staticmethod
    def forward(ctx, acc, alpha, background, color, depth, cfg: LossConfig):
        value, error, grad_acc, grad_alpha = fused_loss_cpu(acc, alpha, background, color, depth, cfg)
        ctx.save_for_backward(grad_acc, grad_alpha)
        ctx.mark_non_differentiable(error)
        return torch.tensor(value, dtype=torch.float32), error

    @staticmethod
    def backward(ctx, grad_out, _grad_error):
        grad_acc, grad_alpha = ctx.saved_tensors
        return grad_out * grad_acc, grad_out * grad_alpha, None, None, None, None


def fused_applies(out: RenderOutput, color: torch.Tensor) -> bool:
    """Whether :class:`_FusedLossCPU` computes this loss: a render with its accumulations (``cpu`` renderer), all
    float32 on the CPU."""
    if out.raw is None:
        return False
    acc, alpha, _ = out.raw
    return acc.device.type == "cpu" and acc.dtype == torch.float32 and alpha.dtype == torch.float32 and \
        color.dtype == torch.float32


def supervision_loss(out: RenderOutput, color: torch.Tensor, depth: torch.Tensor, cfg: LossConfig):
    """Loss of one training render against its view (color [h, w, 3], depth [h, w] metres, 0 = missing).

    Returns (loss, error [h, w]): the detached per-pixel photometric error that Map-Guided View Scheduling
    accumulates into microcells, so the spatial signal costs no extra render. A ``cpu`` render in float32 takes the
    fused path (:class:`_FusedLossCPU`: the same loss and gradient, differentiated into the compositing's
    accumulations ``out.raw``); every other render the torch formulation below.
    """
    if fused_applies(out, color):
        acc, alpha, background = out.raw
        return _FusedLossCPU.apply(acc, alpha, background, color, depth, cfg)
    return torch_loss(out, color, depth, cfg)


def torch_loss(out: RenderOutput, color: torch.Tensor, depth: torch.Tensor, cfg: LossConfig):
    """:func:`supervision_loss` in torch operators from the finished render (any device and dtype). The depth term's
    valid-pixel count stays a tensor: the mean over the valid pixels needs no read on the host."""
    abs_err = (out.color - color).abs()  # [h, w, 3]
    l1 = abs_err.mean()
    loss = (1.0 - cfg.lambda_dssim) * l1
    if cfg.lambda_dssim > 0:
        loss = loss + cfg.lambda_dssim * dssim(out.color, color)
    if cfg.lambda_depth > 0:
        valid = (depth > 0) & (out.alpha.detach() > cfg.depth_alpha_min)
        # the mean over valid pixels, without gathering them (a masked gather's backward is slow); 0 without any
        err = torch.where(valid, (out.depth - depth).abs(), torch.zeros((), dtype=out.depth.dtype,
                                                                           device=out.depth.device))
        n_valid = valid.sum().clamp_min(1).to(err.dtype)
        loss = loss + err.sum() * (cfg.lambda_depth / n_valid)
    return loss, abs_err.detach().mean(-1)
