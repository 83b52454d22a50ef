""":func:`.device_reference_loss.fused_loss` in two Triton launches. The first, per block of pixels, finishes the
colour (background), writes the error map and the block's sums (L1, depth L1, valid pixels); per block of the
'valid' D-SSIM positions it forms the five windowed moments, SSIM and SSIM's derivatives with respect to the
moments. The second, per block of pixels, reads every block's sums (so n_valid never leaves the device), scatters
D-SSIM's derivatives back through the transposed window and writes d loss / d acc, d loss / d alpha; its first
program writes the loss. The window's taps are host floats."""

from __future__ import annotations

import torch
import triton.language as tl

from .device_reference_loss import C1, C2, DEPTH_ALPHA_EPS, dssim_window, window_taps
from .triton_launch import cdiv, kernel, launch, pow2

_C1, _C2, _EPS = tl.constexpr(C1), tl.constexpr(C2), tl.constexpr(DEPTH_ALPHA_EPS)


@kernel
def _loss_fwd(acc, alpha, bg, color, depth, error, dbuf, parts, HW, W, HOWO, WO, alpha_min, inv_n, taps,
              HAS_BG: tl.constexpr, DSSIM: tl.constexpr, WIN: tl.constexpr, BLOCK: tl.constexpr):
    p = tl.program_id(0)
    q = p * BLOCK + tl.arange(0, BLOCK)
    ok = q < HW
    a = tl.load(alpha + q, mask=ok, other=0.0)
    err = tl.zeros([BLOCK], tl.float32)
    for c in tl.static_range(3):
        x = tl.load(acc + q * 4 + c, mask=ok, other=0.0)
        if HAS_BG:
            x = x + (1.0 - a) * tl.load(bg + c)
        err += tl.abs(x - tl.load(color + q * 3 + c, mask=ok, other=0.0))
    err = tl.where(ok, err, 0.0)  # past the image: no background either
    tl.store(error + q, err / 3.0, mask=ok)
    rd = tl.load(depth + q, mask=ok, other=0.0)
    valid = ok & (rd > 0) & (a > alpha_min)
    pd = tl.where(a > _EPS, tl.load(acc + q * 4 + 3, mask=ok, other=0.0) / tl.where(a > _EPS, a, 1.0), 0.0)
    tl.store(parts + p * 4 + 0, tl.sum(err.to(tl.float64), 0))
    tl.store(parts + p * 4 + 1, tl.sum(tl.where(valid, tl.abs(pd - rd), 0.0).to(tl.float64), 0))
    tl.store(parts + p * 4 + 2, tl.sum(valid.to(tl.float64), 0))
    ssum = tl.zeros([BLOCK], tl.float64)
    if DSSIM:
        o = p * BLOCK + tl.arange(0, BLOCK)
        okp = o < HOWO
        base = (o // WO) * W + o % WO  # the window's top-left pixel
        for c in tl.static_range(3):
            mx, my = tl.zeros([BLOCK], tl.float32), tl.zeros([BLOCK], tl.float32)
            exx, eyy, exy = tl.zeros([BLOCK], tl.float32), tl.zeros([BLOCK], tl.float32), tl.zeros([BLOCK], tl.float32)
            for ki in tl.static_range(WIN):
                for kj in tl.static_range(WIN):
                    px = base + ki * W + kj
                    w = taps[ki] * taps[kj]
                    x = tl.load(acc + px * 4 + c, mask=okp, other=0.0)
                    if HAS_BG:
                        x = x + (1.0 - tl.load(alpha + px, mask=okp, other=0.0)) * tl.load(bg + c)
                    y = tl.load(color + px * 3 + c, mask=okp, other=0.0)
                    mx += w * x
                    my += w * y
                    exx += w * x * x
                    eyy += w * y * y
                    exy += w * x * y
            a1, b1 = 2 * mx * my + _C1, mx * mx + my * my + _C1
            a2, b2 = 2 * (exy - mx * my) + _C2, (exx - mx * mx) + (eyy - my * my) + _C2
            s = (a1 * a2) / (b1 * b2)
            ssum += tl.where(okp, s, 0.0).to(tl.float64)
            f = -s * inv_n
            tl.store(dbuf + (0 * 3 + c) * HOWO + o, f * 2 * (my / a1 - mx / b1 - my / a2 + mx / b2), mask=okp)
            tl.store(dbuf + (1 * 3 + c) * HOWO + o, -f / b2, mask=okp)
            tl.store(dbuf + (2 * 3 + c) * HOWO + o, 2 * f / a2, mask=okp)
    tl.store(parts + p * 4 + 3, tl.sum(ssum, 0))


@kernel
def _loss_bwd(acc, alpha, bg, color, depth, dbuf, parts, loss, grad_acc, grad_alpha, HW, W, HOWO, WO, HO, NP,
              alpha_min, inv_n, w_l1, lam_dssim, lam_depth, taps, HAS_BG: tl.constexpr, DSSIM: tl.constexpr,
              DEPTH: tl.constexpr, WIN: tl.constexpr, BLOCK: tl.constexpr, NPB: tl.constexpr):
    p = tl.program_id(0)
    k = tl.arange(0, NPB)[:, None] * 4 + tl.arange(0, 4)[None, :]
    tot = tl.sum(tl.load(parts + k, mask=k < NP * 4, other=0.0), 0)  # [4]: l1, depth L1, n_valid, sum SSIM
    cols = tl.arange(0, 4)
    l1, dsum = tl.sum(tl.where(cols == 0, tot, 0.0), 0), tl.sum(tl.where(cols == 1, tot, 0.0), 0)
    nv, ssum = tl.sum(tl.where(cols == 2, tot, 0.0), 0), tl.sum(tl.where(cols == 3, tot, 0.0), 0)
    w_depth = tl.where(nv > 0, lam_depth / tl.maximum(nv, 1.0), 0.0)
    if not DEPTH:
        w_depth = w_depth * 0.0
    q = p * BLOCK + tl.arange(0, BLOCK)
    ok = q < HW
    i, j = q // W, q % W
    a = tl.load(alpha + q, mask=ok, other=0.0)
    ga = tl.zeros([BLOCK], tl.float32)
    for c in tl.static_range(3):
        x = tl.load(acc + q * 4 + c, mask=ok, other=0.0)
        if HAS_BG:
            x = x + (1.0 - a) * tl.load(bg + c)
        y = tl.load(color + q * 3 + c, mask=ok, other=0.0)
        d = x - y
        g = w_l1 * tl.where(d > 0, 1.0, tl.where(d < 0, -1.0, 0.0))
        if DSSIM:
            t0, t1, t2 = tl.zeros([BLOCK], tl.float32), tl.zeros([BLOCK], tl.float32), tl.zeros([BLOCK], tl.float32)
            for ki in tl.static_range(WIN):
                for kj in tl.static_range(WIN):
                    oi, oj = i - ki, j - kj
                    m = ok & (oi >= 0) & (oi < HO) & (oj >= 0) & (oj < WO)
                    o = oi * WO + oj
                    w = taps[ki] * taps[kj]
                    t0 += w * tl.load(dbuf + c * HOWO + o, mask=m, other=0.0)
                    t1 += w * tl.load(dbuf + (3 + c) * HOWO + o, mask=m, other=0.0)
                    t2 += w * tl.load(dbuf + (6 + c) * HOWO + o, mask=m, other=0.0)
            g += lam_dssim * (t0 + 2 * x * t1 + y * t2)
        tl.store(grad_acc + q * 4 + c, g, mask=ok)
        if HAS_BG:
            ga -= g * tl.load(bg + c)
    gd = tl.zeros([BLOCK], tl.float32)
    if DEPTH:
        rd = tl.load(depth + q, mask=ok, other=0.0)
        ad = tl.load(acc + q * 4 + 3, mask=ok, other=0.0)
        use = ok & (rd > 0) & (a > alpha_min) & (a > _EPS)
        a_safe = tl.where(use, a, 1.0)
        dd = ad / a_safe - rd
        gp = tl.where(use, w_depth * tl.where(dd > 0, 1.0, tl.where(dd < 0, -1.0, 0.0)), 0.0)
        gd = gp / a_safe
        ga -= gp * ad / (a_safe * a_safe)
    tl.store(grad_acc + q * 4 + 3, gd, mask=ok)
    tl.store(grad_alpha + q, ga, mask=ok)
    value = w_l1 * l1 + w_depth * dsum
    if DSSIM:
        value += lam_dssim * (1.0 - ssum * inv_n)
    tl.store(loss + tl.arange(0, 1), value.to(tl.float32) + tl.zeros([1], tl.float32), mask=(tl.arange(0, 1) + p) == 0)


def fused_loss(acc, alpha, background, color, depth, lambda_dssim: float, lambda_depth: float,
               alpha_min: float):
    """:func:`.device_reference_loss.fused_loss` (same arguments and outputs) in two launches."""
    h, w = alpha.shape
    dev = alpha.device
    win = dssim_window(h, w)
    dssim = lambda_dssim > 0 and win >= 3
    ho, wo = (h - win + 1, w - win + 1) if dssim else (1, 1)
    block = 1024 if dev.type == "cpu" else 256
    nb = max(1, cdiv(h * w, block))
    f32 = dict(dtype=torch.float32, device=dev)
    acc_c, a_c = acc.detach().contiguous(), alpha.detach().contiguous()
    bg = background.detach().reshape(3).to(torch.float32).contiguous() if background is not None else a_c
    col, dep = color.detach().to(torch.float32).contiguous(), depth.detach().to(torch.float32).contiguous()
    error, dbuf = torch.empty(h, w, **f32), torch.empty(9 * ho * wo if dssim else 1, **f32)
    parts = torch.empty(nb * 4, dtype=torch.float64, device=dev)
    taps = window_taps(win) if dssim else (0.0,)
    inv_n = 1.0 / (3 * ho * wo)
    flags = dict(HAS_BG=background is not None, DSSIM=dssim, WIN=win if dssim else 1, BLOCK=block)
    launch(_loss_fwd, (nb,), acc_c, a_c, bg, col, dep, error, dbuf, parts, h * w, w, ho * wo, wo,
           float(alpha_min), inv_n, taps, **flags)
    loss, grad_acc, grad_alpha = torch.empty((), **f32), torch.empty(h, w, 4, **f32), torch.empty(h, w, **f32)
    launch(_loss_bwd, (nb,), acc_c, a_c, bg, col, dep, dbuf, parts, loss, grad_acc, grad_alpha, h * w, w, ho * wo,
           wo, ho, nb, float(alpha_min), inv_n, (1.0 - lambda_dssim) / (3 * h * w), float(lambda_dssim),
           float(lambda_depth), taps, DEPTH=lambda_depth > 0, NPB=pow2(nb), **flags)
    return loss, error, grad_acc, grad_alpha
