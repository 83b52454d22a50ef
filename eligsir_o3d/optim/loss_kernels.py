"""Numba kernels of the fused supervision loss on the CPU (``optim.losses.supervision_loss`` of a ``cpu`` render).

The ``cpu`` renderer hands the loss its compositing's accumulations (``RenderOutput.raw``: colour and depth summed
front to back [H, W, 4], alpha [H, W], the background). From them one pass builds the finished colour and depth
(:func:`.render.base.finish`: background composited, depth normalised by alpha), the photometric L1, the
per-pixel error map that view scheduling reads, and the depth L1 over the valid pixels; D-SSIM is the kernel of
:mod:`.dssim_kernels`; a second pass chains every term's gradient back to the accumulations. The loss is a sum
of means, so its gradient is known at forward time: autograd's backward only scales it. In torch the same loss
is ~20 small operations forward and as many backward, ~15 % of a 1/4-scale update on the CPU; tested against
that formulation (value and gradient) in tests/optim/test_fused_loss.py.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from ..runtime.jit import full_width_vectors
from ..runtime.jit import jit as _jit

DEPTH_ALPHA_EPS = 1e-4  # finish(): depth = acc_depth / alpha where alpha > this, else 0


@_jit
def loss_terms(acc, alpha, bg, has_bg, ref, ref_depth, alpha_min, x, y, error, row_terms):
    """acc [H, W, 4] (rgb, depth sums), alpha [H, W], bg [3], ref [H, W, 3], ref_depth [H, W] (0 = missing).

    Fills x, y [3, H, W] (finished colour and reference, D-SSIM's layout), error [H, W] (mean absolute colour
    error) and row_terms [H, 3] (per row: sum |colour error|, sum |depth error| and count over the valid pixels:
    reference depth > 0 and alpha > ``alpha_min``), in float64."""
    h, w = alpha.shape
    for i in prange(h):
        l1 = 0.0
        dsum = 0.0
        nv = 0.0
        for j in range(w):
            a = alpha[i, j]
            om = np.float32(1.0) - a
            e = np.float32(0.0)
            for c in range(3):
                col = acc[i, j, c] + om * bg[c] if has_bg else acc[i, j, c]
                r = np.float32(ref[i, j, c])
                x[c, i, j] = col
                y[c, i, j] = r
                d = abs(col - r)
                e += d
                l1 += d
            error[i, j] = e / np.float32(3.0)
            rd = ref_depth[i, j]
            if rd > 0 and a > alpha_min:
                pd = acc[i, j, 3] / a if a > DEPTH_ALPHA_EPS else np.float32(0.0)
                dsum += abs(pd - rd)
                nv += 1.0
        row_terms[i, 0] = l1
        row_terms[i, 1] = dsum
        row_terms[i, 2] = nv


@_jit
def loss_grad(acc, alpha, bg, has_bg, x, y, ref_depth, alpha_min, w_l1, w_dssim, dssim_grad, w_depth,
              grad_acc, grad_alpha):
    """The loss's gradient with respect to acc [H, W, 4] and alpha [H, W]: ``w_l1 * sign(x - y)`` (the L1's mean
    weight), plus ``w_dssim * dssim_grad`` ([3, H, W], D-SSIM's gradient; ignored when ``w_dssim`` is 0), through
    the background blend; ``w_depth * sign(depth - ref_depth)`` on the valid pixels, through the normalisation."""
    h, w = alpha.shape
    for i in prange(h):
        full_width_vectors()
        for j in range(w):
            a = alpha[i, j]
            ga = np.float32(0.0)
            for c in range(3):
                d = x[c, i, j] - y[c, i, j]
                g = w_l1 * (np.float32(d > 0) - np.float32(d < 0))
                if w_dssim != 0:
                    g += w_dssim * dssim_grad[c, i, j]
                grad_acc[i, j, c] = g
                if has_bg:
                    ga -= g * bg[c]
            # the depth term as selects, not branches (their outcome follows the image, not a pattern)
            rd = ref_depth[i, j]
            ok = (rd > 0) & (a > alpha_min) & (a > DEPTH_ALPHA_EPS)
            dd = acc[i, j, 3] / a - rd
            gp = w_depth * (np.float32(dd > 0) - np.float32(dd < 0))  # d loss / d depth
            gd = gp / a
            gb = ga - gp * acc[i, j, 3] / (a * a)
            grad_acc[i, j, 3] = gd if ok else np.float32(0.0)
            grad_alpha[i, j] = gb if ok else ga
