"""Numba kernel of the D-SSIM loss on the CPU: value and gradient in one pass (``optim.dssim`` on CPU float32).

D-SSIM = 1 - mean over channels and valid window positions of SSIM, with the separable Gaussian window of 3DGS
(11 taps, sigma 1.5, no padding). The loss is a plain mean, so its gradient with respect to the prediction is known
at forward time up to the scalar that autograd passes back: the kernel computes both, and the backward pass only
scales the stored gradient. Per channel c, with the five windowed moments mu_x, mu_y, E[x^2], E[y^2], E[xy]:

    S = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_xx + s_yy + C2))
    dS/dmu_x = S (2 mu_y / A1 - 2 mu_x / B1 - 2 mu_y / A2 + 2 mu_x / B2),  dS/dE[x^2] = -S / B2,  dS/dE[xy] = 2 S / A2
    dL/dx = G^T(dL/dmu_x) + 2 x G^T(dL/dE[x^2]) + y G^T(dL/dE[xy])

where G^T is the transposed (scatter) window. Every pass runs in parallel over image rows, along each row one output
pixel per SIMD lane: the window's taps are a compile-time constant (one kernel per window size, :func:`make`), so
the loop over them unrolls and each pixel's sums stay in registers, added tap by tap in index order (the value and
gradient do not depend on the vector width). Tested against the torch formulation (value and autograd gradient,
float64) in tests/optim/test_optim.py.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from ..runtime.jit import compile_kernel as _compile
from ..runtime.jit import full_width_vectors

C1 = 0.01 ** 2
C2 = 0.03 ** 2


def make(WIN: int):
    """The kernel for a window of WIN taps: ``kernel(x, y, g, grad)`` as :func:`dssim_value_and_grad`."""
    PAD = WIN - 1

    def dssim_kernel(x, y, g, grad):
        nc, h, w = x.shape
        ho, wo = h - WIN + 1, w - WIN + 1
        inv_n = 1.0 / (nc * ho * wo)
        f1, f2 = np.float32(C1), np.float32(C2)
        two = np.float32(2.0)
        hm = np.empty((5, nc, h, wo), np.float32)  # horizontal pass of the five moments
        for r in prange(nc * h):
            full_width_vectors()
            c, i = r // h, r % h
            for j in range(wo):
                s0 = np.float32(0.0)
                s1 = np.float32(0.0)
                s2 = np.float32(0.0)
                s3 = np.float32(0.0)
                s4 = np.float32(0.0)
                for k in range(WIN):
                    gk = g[k]
                    a = x[c, i, j + k]
                    b = y[c, i, j + k]
                    s0 += gk * a
                    s1 += gk * b
                    s2 += gk * a * a
                    s3 += gk * b * b
                    s4 += gk * a * b
                hm[0, c, i, j] = s0
                hm[1, c, i, j] = s1
                hm[2, c, i, j] = s2
                hm[3, c, i, j] = s3
                hm[4, c, i, j] = s4
        # vertical pass, SSIM and dL/d(mu_x, E[x^2], E[xy]) on the valid grid; each row's SSIM summed in order
        d = np.empty((3, nc, ho, wo), np.float32)
        row_sum = np.zeros(nc * ho, np.float64)
        for r in prange(nc * ho):
            full_width_vectors()
            c, i = r // ho, r % ho
            ss = np.empty(wo, np.float32)
            for j in range(wo):
                mx = np.float32(0.0)
                my = np.float32(0.0)
                exx = np.float32(0.0)
                eyy = np.float32(0.0)
                exy = np.float32(0.0)
                for k in range(WIN):
                    gk = g[k]
                    mx += gk * hm[0, c, i + k, j]
                    my += gk * hm[1, c, i + k, j]
                    exx += gk * hm[2, c, i + k, j]
                    eyy += gk * hm[3, c, i + k, j]
                    exy += gk * hm[4, c, i + k, j]
                a1 = two * mx * my + f1
                b1 = mx * mx + my * my + f1
                a2 = two * (exy - mx * my) + f2
                b2 = (exx - mx * mx) + (eyy - my * my) + f2
                s = (a1 * a2) / (b1 * b2)
                ss[j] = s
                f = -s * np.float32(inv_n)
                d[0, c, i, j] = f * two * (my / a1 - mx / b1 - my / a2 + mx / b2)
                d[1, c, i, j] = -f / b2
                d[2, c, i, j] = two * f / a2
            acc = 0.0
            for j in range(wo):
                acc += ss[j]
            row_sum[r] = acc
        # transposed vertical pass (scatter rows back), each row padded by WIN - 1 zeros on both sides (an added
        # +0 changes no sum), so that the transposed horizontal pass gathers every output pixel's taps
        tv = np.zeros((3, nc, h, wo + 2 * PAD), np.float32)
        for r in prange(nc * h):
            full_width_vectors()
            c, i = r // h, r % h
            for k in range(max(0, i - ho + 1), min(WIN, i + 1)):
                gk = g[k]
                for q in range(3):
                    for j in range(wo):
                        tv[q, c, i, PAD + j] += gk * d[q, c, i - k, j]
        for r in prange(nc * h):  # transposed horizontal pass and the chain rule through x^2 and xy
            full_width_vectors()
            c, i = r // h, r % h
            for jj in range(w):
                t0 = np.float32(0.0)
                t1 = np.float32(0.0)
                t2 = np.float32(0.0)
                for k in range(WIN):
                    gk = g[k]
                    t0 += gk * tv[0, c, i, PAD + jj - k]
                    t1 += gk * tv[1, c, i, PAD + jj - k]
                    t2 += gk * tv[2, c, i, PAD + jj - k]
                grad[c, i, jj] = t0 + two * x[c, i, jj] * t1 + y[c, i, jj] * t2
        return 1.0 - row_sum.sum() * inv_n

    return _compile(parallel=True)(dssim_kernel)


_kernels: dict[int, object] = {}


def dssim_value_and_grad(x, y, g, grad):
    """x, y [C, H, W] float32 (prediction, reference); g [win] float32 window; fills grad [C, H, W] with
    d(D-SSIM)/dx and returns D-SSIM (float64 accumulation)."""
    win = g.shape[0]
    if win not in _kernels:
        _kernels[win] = make(win)
    return _kernels[win](x, y, g, grad)
