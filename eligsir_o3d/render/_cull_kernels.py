"""Numba kernels of the view-culled update (:mod:`.culling`): the conservative view test over the whole map and the
gather of the rows one view touched.

- :func:`frustum_rows`: the ids (ascending) of the Gaussians whose screen footprint, by a bound that is never
  smaller than the renderer's 3-sigma radius, can reach the image; one pass over the raw means and log scales.
- :func:`group_boxes`, :func:`groups_hit`, :func:`listed_rows`: the same test through a spatial index of the rows
  (:mod:`.cell_index`): each group's box of means and largest scale, a bound on the groups, the row test over the
  rows of the groups kept.

Both run ``prange`` over blocks of rows, so they use the threads numba may use. Compiled lazily on first use and
cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..runtime.fmath import LOG2E, SIG_CLAMP, exp2_neg
from ..runtime.jit import compile_kernel, full_width_vectors
from ._cpu_kernels import HALF, ONE, ZERO, _jit, _jit_serial

CHUNK = 16384  # rows per task of frustum_rows


# ``njit(parallel, fastmath, cache)``: the view test is a bound with slack, so reassociation is harmless and lets
# LLVM vectorise its loop.
_jit_fast = compile_kernel(parallel=True, fastmath=True)


def _make_counts(listed: bool):
    """The view test over rows in chunks: ``listed`` False, chunk c is rows first[c]..last[c] - 1 of the map; True,
    it is positions first[c]..last[c] - 1 of the row list ``rows`` (a cell index's groups, :mod:`.cell_index`).
    One kernel body for both (``listed`` is a closure constant: numba prunes the branch and keys its cache on it)."""

    def frustum_counts(means, log_scales, rows, first, last, V, cam, mask, counts):
        """mask[i] = 1 where the i-th row may reach the image (see :func:`frustum_rows`); counts[c] = ones in chunk
        c. Branch-free float32 (a vector loop); the largest scale bounded by a power of two (exponent bits, no exp)."""
        fx, fy, cx, cy = np.float32(cam[0]), np.float32(cam[1]), np.float32(cam[2]), np.float32(cam[3])
        w, h, jb2 = np.float32(cam[4] - 0.5), np.float32(cam[5] - 0.5), np.float32(cam[7])
        lp = np.float32(cam[8])  # the low-pass + 0.32 of the radius formula's clamp
        near = np.float32(cam[6] * (1.0 - 1e-3) - 1e-6)  # below the renderer's near plane: float32 rounding of z
        v00, v01, v02, v03 = np.float32(V[0, 0]), np.float32(V[0, 1]), np.float32(V[0, 2]), np.float32(V[0, 3])
        v10, v11, v12, v13 = np.float32(V[1, 0]), np.float32(V[1, 1]), np.float32(V[1, 2]), np.float32(V[1, 3])
        v20, v21, v22, v23 = np.float32(V[2, 0]), np.float32(V[2, 1]), np.float32(V[2, 2]), np.float32(V[2, 3])
        for c in prange(counts.shape[0]):
            full_width_vectors()
            k = 0
            for i in range(first[c], last[c]):
                if listed:
                    g = rows[i]
                else:
                    g = i
                mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
                x = v00 * mx + v01 * my + v02 * mz + v03
                y = v10 * mx + v11 * my + v12 * mz + v13
                z = v20 * mx + v21 * my + v22 * mz + v23
                ls = max(log_scales[g, 0], max(log_scales[g, 1], log_scales[g, 2]))
                # exp(ls) = 2^t from above (within 6.2 %): 2^floor(t) (1 + frac(t)), 2^f being convex on [0, 1];
                # the power of two from exponent bits (no exp); beyond 2^16 m: always in
                t = min(max(ls * LOG2E, -np.float32(125.0)), SIG_CLAMP)
                e = np.float32(math.floor(t))
                s = exp2_neg(max(-e, ZERO)) / exp2_neg(max(e, ZERO)) * (ONE + (t - e))
                zs = max(z, near)
                iz = ONE / zs
                # ||J||_F^2 s^2 bounds the largest eigenvalue of J Sigma J^T; + the low-pass + 0.32 of the radius
                # formula's clamp; + 2 px for the ceil and float32 rounding of the renderer's means2d
                r = np.float32(3.003) * np.sqrt(s * s * jb2 * iz * iz + lp) + np.float32(2.0)
                u = fx * x * iz + cx
                v = fy * y * iz + cy
                inside = (u + r > -HALF) & (u - r < w) & (v + r > -HALF) & (v - r < h)
                hit = (z > near) & (inside | (ls * LOG2E > SIG_CLAMP))
                mask[i] = np.uint8(hit)
                k += np.int64(hit)
            counts[c] = k

    return _jit_fast(frustum_counts)


_frustum_counts = _make_counts(False)
_listed_counts = _make_counts(True)


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
    bounds = np.minimum(np.arange(chunks + 1, dtype=np.int64) * CHUNK, n)
    _frustum_counts(means, log_scales, bounds, bounds[:-1], bounds[1:], V, cam, mask, counts)
    starts = np.zeros(chunks, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    out = np.empty(int(counts.sum()), np.int64)
    _gather_rows(mask, starts, out)
    return out


@_jit
def group_boxes(means, log_scales, order, starts, groups, boxes):
    """boxes[g] = (min x, y, z, max x, y, z, largest log scale) of the rows order[starts[g]:starts[g + 1]], for
    every group g in ``groups``."""
    for k in prange(groups.shape[0]):
        g = groups[k]
        lo0 = lo1 = lo2 = np.float32(np.inf)
        hi0 = hi1 = hi2 = ls = np.float32(-np.inf)
        for i in range(starts[g], starts[g + 1]):
            r = order[i]
            x, y, z = means[r, 0], means[r, 1], means[r, 2]
            lo0, lo1, lo2 = min(lo0, x), min(lo1, y), min(lo2, z)
            hi0, hi1, hi2 = max(hi0, x), max(hi1, y), max(hi2, z)
            ls = max(ls, max(log_scales[r, 0], max(log_scales[r, 1], log_scales[r, 2])))
        boxes[g, 0], boxes[g, 1], boxes[g, 2] = lo0, lo1, lo2
        boxes[g, 3], boxes[g, 4], boxes[g, 5], boxes[g, 6] = hi0, hi1, hi2, ls


@_jit_serial
def groups_hit(boxes, V, cam):
    """keep [G] uint8: 0 only where no row of group g can pass the row test (:func:`_make_counts`), whatever its
    means in the box and its log scales up to the box's largest. The row test keeps a row in front of the near
    plane only if, for each image side, a linear function of its camera-frame point stays below A s (with r z <=
    A s + B z, r the test's radius, z > 0): right fx x + (cx - w - B) z, left -fx x - (cx + 1/2 + B) z, and
    likewise in y. A group is dropped where one side's minimum over the box (float64, the box widened for float32
    rounding, B by half a pixel) is at least A times its largest scale (exp bounded by 1.07 as the row test's 2^t
    by 1.062), or the box lies wholly behind the near plane."""
    fx, fy, cx, cy, w, h = cam[0], cam[1], cam[2], cam[3], cam[4] - 0.5, cam[5] - 0.5
    near = cam[6] * (1.0 - 1e-3) - 1e-6
    a_s = 3.003 * math.sqrt(cam[7]) * 1.01
    b = 3.003 * math.sqrt(cam[8]) * 1.01 + 2.5
    sides = np.array([[fx, 0.0, cx - w - b], [-fx, 0.0, -(cx + 0.5 + b)],
                      [0.0, fy, cy - h - b], [0.0, -fy, -(cy + 0.5 + b)]])
    R, t = np.ascontiguousarray(V[:3, :3]), np.ascontiguousarray(V[:3, 3])
    world = sides @ R  # each side's linear function of the world point (without its constant)
    consts = sides @ t
    keep = np.empty(boxes.shape[0], np.uint8)
    for g in range(boxes.shape[0]):
        ls = np.float64(boxes[g, 6])
        if ls * 1.4426950408889634 > 15.99:
            keep[g] = 1  # the row test keeps such rows wherever they are in front
            continue
        s_max = math.exp(ls) * 1.07
        lo0, lo1, lo2 = np.float64(boxes[g, 0]), np.float64(boxes[g, 1]), np.float64(boxes[g, 2])
        hi0, hi1, hi2 = np.float64(boxes[g, 3]), np.float64(boxes[g, 4]), np.float64(boxes[g, 5])
        c0, c1, c2 = 0.5 * (lo0 + hi0), 0.5 * (lo1 + hi1), 0.5 * (lo2 + hi2)
        e0 = 0.5 * (hi0 - lo0) + 1e-4 * (abs(c0) + 1.0)  # widened for the float32 rounding of the row test
        e1 = 0.5 * (hi1 - lo1) + 1e-4 * (abs(c1) + 1.0)
        e2 = 0.5 * (hi2 - lo2) + 1e-4 * (abs(c2) + 1.0)
        z_max = R[2, 0] * c0 + R[2, 1] * c1 + R[2, 2] * c2 + t[2] + abs(R[2, 0]) * e0 + abs(R[2, 1]) * e1 + \
            abs(R[2, 2]) * e2
        out = z_max <= near
        for k in range(4):
            f_min = consts[k] + world[k, 0] * c0 + world[k, 1] * c1 + world[k, 2] * c2 - abs(world[k, 0]) * e0 - \
                abs(world[k, 1]) * e1 - abs(world[k, 2]) * e2
            out = out | (f_min >= a_s * s_max)
        keep[g] = 0 if out else 1
    return keep


@_jit_serial
def mark_groups(group_of, rows, n, dirty):
    """dirty[group_of[r]] = True for the rows r < n (the indexed ones) of ``rows``."""
    for i in range(rows.shape[0]):
        r = rows[i]
        if r < n:
            dirty[group_of[r]] = True


@_jit
def _gather_listed(order, first, last, mask, starts, out):
    for c in prange(first.shape[0]):
        k = starts[c]
        for i in range(first[c], last[c]):
            if mask[i]:
                out[k] = order[i]
                k += 1


def listed_rows(means, log_scales, order, starts, keep, V, cam) -> tuple[np.ndarray, int]:
    """(ids the row test keeps among the rows of the groups with ``keep``, in group order; how many were tested)."""
    kept = np.flatnonzero(keep)
    first, last = starts[kept], starts[kept + 1]
    mask = np.empty(order.shape[0], np.uint8)
    counts = np.empty(kept.size, np.int64)
    if kept.size:
        _listed_counts(means, log_scales, order, first, last, V, cam, mask, counts)
    offs = np.zeros(kept.size, np.int64)
    np.cumsum(counts[:-1], out=offs[1:])
    out = np.empty(int(counts.sum()), np.int64)
    if kept.size:
        _gather_listed(order, first, last, mask, offs, out)
    return out, int((last - first).sum())


@_jit
def _gather_view(srcs, rows, dsts):
    """dsts[t][i] = srcs[t][rows[i]] for every parameter t (2-D float32 arrays, rows first): one pass over the
    view's rows for all of them."""
    for i in prange(rows.shape[0]):
        r = rows[i]
        for t in range(len(srcs)):
            s, d = srcs[t], dsts[t]
            for j in range(s.shape[1]):
                d[i, j] = s[r, j]
