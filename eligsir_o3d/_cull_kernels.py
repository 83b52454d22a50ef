"""Numba kernels of the view-culled update (:mod:`.culling`): the conservative view test over the whole map and the
Adam step over the rows one view touched.

- :func:`frustum_rows`: the ids (ascending) of the Gaussians whose screen footprint, by a bound that is never
  smaller than the renderer's 3-sigma radius, can reach the image; one pass over the raw means and log scales.
  On a 1M-Gaussian map it is the only per-update work that grows with the map.
- :func:`adam_rows_at`: Adam over the selected rows of every parameter (the gradient rows of a view's gathered
  leaves), each row with its own step size and bias correction; rows outside the selection are not read or written.

Both run ``prange`` over blocks of rows, so they use the threads numba may use. Compiled lazily on first use and
cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from .render._cpu_kernels import _jit

CHUNK = 16384  # rows per task of frustum_rows


@_jit
def _frustum_counts(means, log_scales, V, cam, mask, counts):
    """mask[g] = 1 where Gaussian g may reach the image (see :func:`frustum_rows`); counts[c] = ones in chunk c."""
    fx, fy, cx, cy, w, h, near, jb2 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7]
    n = means.shape[0]
    for c in prange(counts.shape[0]):
        k = 0
        for g in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            mx, my, mz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
            z = V[2, 0] * mx + V[2, 1] * my + V[2, 2] * mz + V[2, 3]
            hit = 0
            if z > near:
                x = V[0, 0] * mx + V[0, 1] * my + V[0, 2] * mz + V[0, 3]
                y = V[1, 0] * mx + V[1, 1] * my + V[1, 2] * mz + V[1, 3]
                ls = max(log_scales[g, 0], max(log_scales[g, 1], log_scales[g, 2]))
                s = math.exp(min(np.float64(ls), 80.0))
                # ||J||_F^2 s^2 bounds the largest eigenvalue of J Sigma J^T; + 0.3 low-pass + 0.32 of the radius
                # formula's clamp; + 2 px for the ceil and float32 rounding of the renderer's means2d
                r = 3.0 * math.sqrt(s * s * jb2 / (z * z) + 0.62) * 1.001 + 2.0
                u = fx * x / z + cx
                v = fy * y / z + cy
                if u + r > -0.5 and u - r < w - 0.5 and v + r > -0.5 and v - r < h - 0.5:
                    hit = 1
            mask[g] = hit
            k += hit
        counts[c] = k


@_jit
def _gather_rows(mask, starts, out):
    n = mask.shape[0]
    for c in prange(starts.shape[0]):
        k = starts[c]
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
def _adam_at(ps, gs, ms, vs, hyper, a_rows, b_rows, widths, rows):
    """For every parameter t and selected row r (map row rows[r]): Adam on the ``widths[t]`` elements of that row
    of ps[t]/ms[t]/vs[t] (flat, the whole map) from gradient row r of gs[t] (flat, the selected rows only), with
    step -a_rows[t][r] / bias correction 1 folded in and b_rows[t][r] = sqrt(bias correction 2);
    hyper[t] = (1 - beta1, beta2, 1 - beta2, eps)."""
    for t in range(len(ps)):
        p, g, m, v, a, b, wd = ps[t], gs[t], ms[t], vs[t], a_rows[t], b_rows[t], widths[t]
        w, b2, w2, eps = hyper[t, 0], hyper[t, 1], hyper[t, 2], hyper[t, 3]
        for r in prange(rows.shape[0]):
            ar, br = a[r], b[r]
            base = rows[r] * wd
            for j in range(wd):
                i = base + j
                gi = g[r * wd + j]
                mi = m[i] + w * (gi - m[i])
                vi = v[i] * b2 + w2 * gi * gi
                m[i] = mi
                v[i] = vi
                p[i] = p[i] + ar * (mi / (np.sqrt(vi) / br + eps))


def adam_rows_at(items, rows: np.ndarray) -> None:
    """One Adam step per item ``(param, grad_rows, exp_avg, exp_avg_sq, a_rows, b_rows, (1 - beta1, beta2,
    1 - beta2, eps))`` on map rows ``rows`` [M] int64: param/exp_avg/exp_avg_sq float32 CPU tensors of the whole
    map [N, ...], grad_rows [M, ...] the selected rows' gradients, a_rows/b_rows [M] float32."""
    if not items or rows.shape[0] == 0:
        return
    f = lambda t: t.detach().contiguous().view(-1).numpy()  # noqa: E731
    ps = tuple(it[0].detach().view(-1).numpy() for it in items)
    ms = tuple(it[2].view(-1).numpy() for it in items)
    vs = tuple(it[3].view(-1).numpy() for it in items)
    widths = np.array([it[0].numel() // max(it[0].shape[0], 1) for it in items], np.int64)
    _adam_at(ps, tuple(f(it[1]) for it in items), ms, vs, np.array([it[6] for it in items], np.float32),
             tuple(f(it[4]) for it in items), tuple(f(it[5]) for it in items), widths, rows)
