"""Numba kernel of the D-SSIM loss on the CPU: value and gradient in one pass (``optim.dssim`` on CPU float32).

D-SSIM = 1 - mean over channels and valid window positions of SSIM, with the separable Gaussian window of 3DGS
(11 taps, sigma 1.5, no padding). The loss is a plain mean, so its gradient with respect to the prediction is known
at forward time up to the scalar that autograd passes back: the kernel computes both, and the backward pass only
scales the stored gradient. Per channel c, with the five windowed moments mu_x, mu_y, E[x^2], E[y^2], E[xy]:

    S = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_xx + s_yy + C2))
    dS/dmu_x = S (2 mu_y / A1 - 2 mu_x / B1 - 2 mu_y / A2 + 2 mu_x / B2),  dS/dE[x^2] = -S / B2,  dS/dE[xy] = 2 S / A2
    dL/dx = G^T(dL/dmu_x) + 2 x G^T(dL/dE[x^2]) + y G^T(dL/dE[xy])

where G^T is the transposed (scatter) window. Every pass runs in parallel over image rows. Tested against the
torch formulation (value and autograd gradient, float64) in tests/optim/test_optim.py.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from ..runtime.jit import jit as _jit

C1 = 0.01 ** 2
C2 = 0.03 ** 2


@_jit
def dssim_value_and_grad(x, y, g, grad):
    """x, y [C, H, W] float32 (prediction, reference); g [win] float32 window; fills grad [C, H, W] with
    d(D-SSIM)/dx and returns D-SSIM (float64 accumulation). Inner loops run along image rows (SIMD)."""
    nc, h, w = x.shape
    win = g.shape[0]
    ho, wo = h - win + 1, w - win + 1
    inv_n = 1.0 / (nc * ho * wo)
    f1, f2 = np.float32(C1), np.float32(C2)
    two = np.float32(2.0)
    # horizontal pass of the five moments: [5, C, H, Wo]
    hm = np.zeros((5, nc, h, wo), np.float32)
    for r in prange(nc * h):
        c, i = r // h, r % h
        for k in range(win):
            gk = g[k]
            for j in range(wo):
                a = x[c, i, j + k]
                b = y[c, i, j + k]
                hm[0, c, i, j] += gk * a
                hm[1, c, i, j] += gk * b
                hm[2, c, i, j] += gk * a * a
                hm[3, c, i, j] += gk * b * b
                hm[4, c, i, j] += gk * a * b
    # vertical pass, SSIM and dL/d(mu_x, E[x^2], E[xy]) on the valid grid: [3, C, Ho, Wo]
    d = np.empty((3, nc, ho, wo), np.float32)
    row_sum = np.zeros(nc * ho, np.float64)
    for r in prange(nc * ho):
        c, i = r // ho, r % ho
        m = np.zeros((5, wo), np.float32)
        for k in range(win):
            gk = g[k]
            for q in range(5):
                for j in range(wo):
                    m[q, j] += gk * hm[q, c, i + k, j]
        acc = 0.0
        for j in range(wo):
            mx, my, exx, eyy, exy = m[0, j], m[1, j], m[2, j], m[3, j], m[4, j]
            a1 = two * mx * my + f1
            b1 = mx * mx + my * my + f1
            a2 = two * (exy - mx * my) + f2
            b2 = (exx - mx * mx) + (eyy - my * my) + f2
            s = (a1 * a2) / (b1 * b2)
            acc += s
            f = -s * np.float32(inv_n)  # dL/dS = -1/N
            d[0, c, i, j] = f * two * (my / a1 - mx / b1 - my / a2 + mx / b2)
            d[1, c, i, j] = -f / b2
            d[2, c, i, j] = two * f / a2
        row_sum[r] = acc
    # transposed vertical pass (scatter rows back): [3, C, H, Wo]
    tv = np.zeros((3, nc, h, wo), np.float32)
    for r in prange(nc * h):
        c, i = r // h, r % h
        for k in range(max(0, i - ho + 1), min(win, i + 1)):
            gk = g[k]
            for q in range(3):
                for j in range(wo):
                    tv[q, c, i, j] += gk * d[q, c, i - k, j]
    # transposed horizontal pass and the chain rule through x^2 and xy
    for r in prange(nc * h):
        c, i = r // h, r % h
        t = np.zeros((3, w), np.float32)
        for k in range(win):
            gk = g[k]
            for q in range(3):
                for j in range(wo):
                    t[q, j + k] += gk * tv[q, c, i, j]
        for j in range(w):
            grad[c, i, j] = t[0, j] + two * x[c, i, j] * t[1, j] + y[c, i, j] * t[2, j]
    return 1.0 - row_sum.sum() * inv_n
