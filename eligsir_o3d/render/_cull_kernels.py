"""Numba kernels of the view-culled update (:mod:`.culling`): the conservative view test over the whole map and the
Adam step over the rows one view touched.

- :func:`frustum_rows`: the ids (ascending) of the Gaussians whose screen footprint, by a bound that is never
  smaller than the renderer's 3-sigma radius, can reach the image; one pass over the raw means and log scales.
  On a 1M-Gaussian map it is the only per-update work that grows with the map.
- :func:`_adam_view`: Adam over the selected rows of every parameter (the gradient rows of a view's gathered
  leaves) with the rows' bookkeeping (step counts, step sizes, bias corrections); rows outside the selection are
  not read or written.

Both run ``prange`` over blocks of rows, so they use the threads numba may use. Compiled lazily on first use and
cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import numpy as np
from numba import prange

import math

import numba

from ._cpu_kernels import HALF, LOG2E, ONE, SIG_CLAMP, ZERO, _exp2_neg, _jit

CHUNK = 16384  # rows per task of frustum_rows


def _jit_fast(fn):
    """``njit(parallel, fastmath, cache)``: the view test is a bound with slack, so reassociation is harmless and
    lets LLVM vectorise its loop; without a writable cache location, an uncached kernel."""
    opts = dict(parallel=True, fastmath=True, nogil=True)
    try:
        return numba.njit(cache=True, **opts)(fn)
    except RuntimeError:
        return numba.njit(cache=False, **opts)(fn)


@_jit_fast
def _frustum_counts(means, log_scales, V, cam, mask, counts):
    """mask[g] = 1 where Gaussian g may reach the image (see :func:`frustum_rows`); counts[c] = ones in chunk c.
    Branch-free float32 (a vector loop); the largest scale bounded by a power of two (exponent bits, no exp)."""
    fx, fy, cx, cy = np.float32(cam[0]), np.float32(cam[1]), np.float32(cam[2]), np.float32(cam[3])
    w, h, jb2 = np.float32(cam[4] - 0.5), np.float32(cam[5] - 0.5), np.float32(cam[7])
    lp = np.float32(cam[8])  # the low-pass + 0.32 of the radius formula's clamp
    near = np.float32(cam[6] * (1.0 - 1e-3) - 1e-6)  # below the renderer's near plane: float32 rounding of z
    v00, v01, v02, v03 = np.float32(V[0, 0]), np.float32(V[0, 1]), np.float32(V[0, 2]), np.float32(V[0, 3])
    v10, v11, v12, v13 = np.float32(V[1, 0]), np.float32(V[1, 1]), np.float32(V[1, 2]), np.float32(V[1, 3])
    v20, v21, v22, v23 = np.float32(V[2, 0]), np.float32(V[2, 1]), np.float32(V[2, 2]), np.float32(V[2, 3])
    n = means.shape[0]
    for c in prange(counts.shape[0]):
        k = 0
        for g in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
            x = v00 * mx + v01 * my + v02 * mz + v03
            y = v10 * mx + v11 * my + v12 * mz + v13
            z = v20 * mx + v21 * my + v22 * mz + v23
            ls = max(log_scales[g, 0], max(log_scales[g, 1], log_scales[g, 2]))
            # exp(ls) = 2^t from above (within 6%): 2^floor(t) (1 + frac(t)), 2^f being convex on [0, 1]; the
            # power of two from exponent bits (no exp); beyond 2^16 m: always in
            t = min(max(ls * LOG2E, -np.float32(125.0)), SIG_CLAMP)
            e = np.float32(math.floor(t))
            s = _exp2_neg(max(-e, ZERO)) / _exp2_neg(max(e, ZERO)) * (ONE + (t - e))
            zs = max(z, near)
            iz = ONE / zs
            # ||J||_F^2 s^2 bounds the largest eigenvalue of J Sigma J^T; + the low-pass + 0.32 of the radius
            # formula's clamp; + 2 px for the ceil and float32 rounding of the renderer's means2d
            r = np.float32(3.003) * np.sqrt(s * s * jb2 * iz * iz + lp) + np.float32(2.0)
            u = fx * x * iz + cx
            v = fy * y * iz + cy
            inside = (u + r > -HALF) & (u - r < w) & (v + r > -HALF) & (v - r < h)
            hit = (z > near) & (inside | (ls * LOG2E > SIG_CLAMP))
            mask[g] = np.uint8(hit)
            k += np.int64(hit)
        counts[c] = k


@_jit
def _gather_rows(mask, starts, out):
    n = mask.shape[0]
    for c in prange(starts.shape[0]):
        k = starts[c]
        if c + 1 < starts.shape[0] and starts[c + 1] == k or c + 1 == starts.shape[0] and out.shape[0] == k:
            continue  # nothing of this chunk in view
        for g in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if mask[g]:
                out[k] = g
                k += 1


def frustum_rows(means: np.ndarray, log_scales: np.ndarray, V: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """int64 ids, ascending, of the Gaussians (means [N, 3] world metres, log_scales [N, 3], float32) that the
    renderer can draw in the view of world-to-camera ``V`` [4, 4] float64 and ``cam`` = (fx, fy, cx, cy, width,
    height, near, jb2) float64, jb2 = the bound of the squared Frobenius norm of the clamped projection Jacobian
    times z^2 (:func:`.culling.camera_bounds`)."""
    n = means.shape[0]
    chunks = max(1, (n + CHUNK - 1) // CHUNK)
    mask = np.empty(n, np.uint8)
    counts = np.empty(chunks, np.int64)
    _frustum_counts(means, log_scales, V, cam, mask, counts)
    starts = np.zeros(chunks, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    out = np.empty(int(counts.sum()), np.int64)
    _gather_rows(mask, starts, out)
    return out


@_jit
def _adam_view(ps, gs, ms, vs, row_steps, hyper, steps, widths, rows, seen, plan):
    """Adam over the view's rows ``rows`` [M] of every parameter t, with the per-row bookkeeping of
    :meth:`.culling.InView.adam_step` in the same pass: row_steps[t][row] += 1; for t = 0 (the means) first
    seen[row] += 1 where the row's gradient is not all zero; then the step size -lr / (1 - beta1^k) and
    sqrt(1 - beta2^k) with k the row's count (plan[0] = 1: exact per row) or steps[t] (the tensor's), times
    means_decay_to^min(seen / means_decay_updates, 1) for the means and min(seen / warmup_updates, 1) for every
    parameter. hyper[t] = (1 - beta1, beta2, 1 - beta2, eps, lr, beta1) (float64); plan = (row bias correction,
    means_decay_to, means_decay_updates, warmup_updates, whether t = 0 is the means: without them there are no
    seen counts and neither schedule applies)."""
    for t in range(len(ps)):
        p, g, m, v, rs, wd = ps[t], gs[t], ms[t], vs[t], row_steps[t], widths[t]
        w, b2, w2, eps = np.float32(hyper[t, 0]), np.float32(hyper[t, 1]), np.float32(hyper[t, 2]), \
            np.float32(hyper[t, 3])
        lr, b1, b2d = hyper[t, 4], hyper[t, 5], hyper[t, 1]
        a_t = np.float32(-lr * (1.0 / (1.0 - b1 ** steps[t])))  # the tensor's count: once, not per row
        b_t = np.float32(math.sqrt(1.0 - b2d ** steps[t]))
        means = t == 0 and plan[4] != 0
        for r in prange(rows.shape[0]):
            row = rows[r]
            rs[row] += np.float32(1.0)
            if means:
                nz = False
                for j in range(wd):
                    nz = nz | (g[r * wd + j] != 0)
                seen[row] += np.float32(1.0) if nz else np.float32(0.0)
            ar, br = a_t, b_t
            if plan[0] != 0:
                k = np.float64(rs[row])
                ar = np.float32(-lr * (1.0 / (1.0 - b1 ** k)))
                br = np.float32(math.sqrt(1.0 - b2d ** k))
            if plan[4] != 0:
                sr = seen[row]
                if means and plan[1] != 1.0:
                    ar = ar * np.float32(np.float32(plan[1]) ** min(sr / np.float32(plan[2]), np.float32(1.0)))
                if plan[3] > 0:
                    ar = ar * min(sr / np.float32(plan[3]), np.float32(1.0))
            base = row * wd
            for j in range(wd):
                i = base + j
                gi = g[r * wd + j]
                mi = m[i] + w * (gi - m[i])
                vi = v[i] * b2 + w2 * gi * gi
                m[i] = mi
                v[i] = vi
                p[i] = p[i] + ar * (mi / (np.sqrt(vi) / br + eps))
