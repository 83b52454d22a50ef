"""Numba kernels of the ``cpu`` renderer: per-tile front-to-back compositing and its back-to-front gradient.

The math is the reference's (``torch_backend.TorchRenderer._tiles``) written per pixel, in float32, in the same
order of operations: ``sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy`` with ``(dx, dy) = pixel - mean``, Gaussians with
``sigma < 0`` or ``alpha < 1/255`` are skipped, ``alpha = min(0.999, o exp(-sigma))``, and a pixel stops before the
Gaussian whose blending would take its transmittance to ``<= 1e-4``. The backward pass follows gsplat's
``rasterize_to_pixels`` backward: it starts from the stored final transmittance and the number of Gaussians the
forward pass walked through, and recovers each Gaussian's transmittance by dividing by ``1 - alpha``.

Work: a pixel walks only the part of its tile's list that can reach its 2x2 pixel block: each tile's list is culled
per block by the bounding box of the ellipse where ``o exp(-sigma) >= 1/255`` (conservatively, so the result is the
same as walking the whole list). On a real scene this cuts the walk from ~540 to ~50 Gaussians per pixel at 160x120.

Parallelism: one tile per task (``prange``), heaviest tiles first, in chunks of one so that the cores share uneven
tiles dynamically. Tiles never write to the same memory: the backward pass writes one gradient row per
(tile, Gaussian) intersection and the caller sums the rows per Gaussian (``index_add_``), so no atomics are needed.

Compilation is lazy (first call) and cached on disk (``cache=True``): numba writes next to this file when the package
folder is writable, else to ``$NUMBA_CACHE_DIR`` or the user cache folder; where none is writable the kernels
still work, compiled once per process.
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np
from numba import prange

TILE = 16
ALPHA_MAX = np.float32(0.999)
ALPHA_MIN = np.float32(1.0 / 255.0)
T_MIN = np.float32(1e-4)
HALF = np.float32(0.5)
ONE = np.float32(1.0)
ZERO = np.float32(0.0)


def _select_threading_layer() -> None:
    """Prefer OpenMP over an old system TBB (numba warns and skips TBB < 2021.6 anyway); the user's choice wins."""
    import os
    if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


_select_threading_layer()


_uncached: list[str] = []


def _compile(parallel: bool):
    """``njit(cache=True)`` decorator; without a writable cache location, fall back to an uncached kernel."""
    def deco(fn):
        opts = dict(parallel=parallel, fastmath=False, nogil=True)
        try:
            return numba.njit(cache=True, **opts)(fn)
        except RuntimeError as err:  # numba: "cannot cache function ...: no locator available for file ..."
            if not _uncached:
                warnings.warn(f"numba cannot cache the cpu renderer's kernels ({err}); they compile in every new "
                              "process. Set NUMBA_CACHE_DIR to a writable folder to keep them.", RuntimeWarning,
                              stacklevel=2)
            _uncached.append(fn.__name__)
            return numba.njit(cache=False, **opts)(fn)
    return deco


_jit = _compile(parallel=True)
_jit_serial = _compile(parallel=False)


SUB = 2  # side of the pixel sub-blocks that get their own culled Gaussian lists
NSUB = TILE // SUB


@_jit_serial
def _gather_tile(means2d, conics, opacities, feats, flat_ids, s, n, x0, y0):
    """Copy tile Gaussians ``flat_ids[s:s + n]`` into contiguous arrays and cull them per SUB x SUB pixel block.

    Returns gp [7, n] (mean x, mean y, conic a, b, c, opacity, sigma bound), gf [n, 4] and, per sub-block,
    the depth-ordered local indices of the Gaussians that can reach it: sub_ids [NSUB * NSUB, n], sub_n [NSUB * NSUB].
    Culling is conservative, so it changes no result: a Gaussian contributes to a pixel only if
    ``o exp(-sigma) >= 1/255``, i.e. ``sigma <= log(255 o)``; the bound keeps a margin of 1e-3 above that (float32
    exp and products err by ~1e-7), and the block test uses the bounding box of the ellipse at that level, widened
    for the float32 rounding of sigma (see below) and by 1e-3 px.
    """
    n_feat = feats.shape[1]
    gp = np.empty((7, n), np.float32)
    gf = np.empty((n, n_feat), np.float32)
    sub_ids = np.empty((NSUB * NSUB, n), np.int32)
    sub_n = np.zeros(NSUB * NSUB, np.int64)
    for k in range(n):
        g = flat_ids[s + k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        a = conics[g, 0]
        b = conics[g, 1]
        c = conics[g, 2]
        o = opacities[g]
        gp[0, k] = mx
        gp[1, k] = my
        gp[2, k] = a
        gp[3, k] = b
        gp[4, k] = c
        gp[5, k] = o
        for f in range(n_feat):
            gf[k, f] = feats[g, f]
        o64 = np.float64(o)
        if not (o64 * 255.0 >= 1.0):  # never reaches alpha 1/255 (NaN-safe: NaN opacities are not culled here)
            if o64 == o64:
                gp[6, k] = np.float32(-1.0)
                continue
        smax = math.log(max(o64 * 255.0, 1.0)) + 1e-3
        gp[6, k] = np.float32(smax) if o64 == o64 else np.float32(np.inf)
        a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)
        det = a64 * c64 - b64 * b64
        sx0, sx1, sy0, sy1 = 0, NSUB - 1, 0, NSUB - 1
        if det > 0.0 and a64 > 0.0 and smax == smax:
            # The kernels evaluate sigma in float32, whose error grows with the conic's condition: at most about
            # 1e-6 * kappa * sigma with kappa = (a + c)^2 / det (~4 for round Gaussians, 1e5 for 300:1 needles).
            s_box = smax * (1.0 + 1e-3 + 2e-6 * (a64 + c64) * (a64 + c64) / det)
            rx = math.sqrt(2.0 * s_box * c64 / det) + 1e-3
            ry = math.sqrt(2.0 * s_box * a64 / det) + 1e-3
            lo_x = (np.float64(mx) - rx - x0) / SUB
            hi_x = (np.float64(mx) + rx - x0) / SUB
            lo_y = (np.float64(my) - ry - y0) / SUB
            hi_y = (np.float64(my) + ry - y0) / SUB
            # a block spans pixel centres [x0 + SUB j, x0 + SUB j + SUB - 1]
            sx0 = max(0, int(math.ceil(lo_x - (SUB - 1.0) / SUB))) if lo_x > -1.0 else 0
            sx1 = min(NSUB - 1, int(math.floor(hi_x))) if hi_x < NSUB else NSUB - 1
            sy0 = max(0, int(math.ceil(lo_y - (SUB - 1.0) / SUB))) if lo_y > -1.0 else 0
            sy1 = min(NSUB - 1, int(math.floor(hi_y))) if hi_y < NSUB else NSUB - 1
        for by in range(sy0, sy1 + 1):
            for bx in range(sx0, sx1 + 1):
                j = by * NSUB + bx
                sub_ids[j, sub_n[j]] = k
                sub_n[j] += 1
    return gp, gf, sub_ids, sub_n


@_jit
def composite_forward(means2d, conics, opacities, feats, offsets, flat_ids, order, tiles_x, width, height,
                      out_feats, out_alpha, out_T, out_last):
    """Blend every tile front to back.

    means2d [N, 2], conics [N, 3], opacities [N], feats [N, 4] (r, g, b, depth; float32); offsets [T + 1] and
    flat_ids [M] (int64): tile t's depth-sorted Gaussians are ``flat_ids[offsets[t]:offsets[t + 1]]``; order [T]: the
    tiles to run, heaviest first. Writes out_feats [H, W, 4] (accumulated features), out_alpha [H, W] (accumulated opacity), out_T [H, W]
    (final transmittance) and out_last [H, W] int32 (how far the pixel walked through its sub-block's list).
    """
    for i in prange(order.shape[0]):
        t = order[i]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        n = offsets[t + 1] - s
        gp, gf, sub_ids, sub_n = _gather_tile(means2d, conics, opacities, feats, flat_ids, s, n,
                                              tx * TILE, ty * TILE)
        for py in range(TILE):
            y = ty * TILE + py
            if y >= height:
                break
            fy = np.float32(y)
            for px in range(TILE):
                x = tx * TILE + px
                if x >= width:
                    break
                fx = np.float32(x)
                sb = (py // SUB) * NSUB + px // SUB
                acc0 = ZERO
                acc1 = ZERO
                acc2 = ZERO
                acc3 = ZERO
                T = ONE
                wsum = ZERO
                walked = 0
                for j in range(sub_n[sb]):
                    k = sub_ids[sb, j]
                    dx = fx - gp[0, k]
                    dy = fy - gp[1, k]
                    sigma = HALF * (gp[2, k] * dx * dx + gp[4, k] * dy * dy) + gp[3, k] * dx * dy
                    if sigma < ZERO or sigma > gp[6, k]:
                        continue
                    alpha = min(ALPHA_MAX, gp[5, k] * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    next_T = T * (ONE - alpha)
                    if next_T <= T_MIN:
                        break
                    w = alpha * T
                    acc0 += w * gf[k, 0]
                    acc1 += w * gf[k, 1]
                    acc2 += w * gf[k, 2]
                    acc3 += w * gf[k, 3]
                    wsum += w
                    T = next_T
                    walked = j + 1
                out_feats[y, x, 0] = acc0
                out_feats[y, x, 1] = acc1
                out_feats[y, x, 2] = acc2
                out_feats[y, x, 3] = acc3
                out_alpha[y, x] = wsum  # = 1 - T up to rounding; summed like the reference
                out_T[y, x] = T
                out_last[y, x] = walked


@_jit
def composite_backward(means2d, conics, opacities, feats, offsets, flat_ids, order, tiles_x, width, height,
                       final_T, last, grad_feats, grad_alpha, v_isect):
    """Back-to-front gradients of ``composite_forward``.

    grad_feats [H, W, 4], grad_alpha [H, W]: gradients of the accumulated outputs. Writes v_isect [M, 10], one row
    per intersection: d/d(mean x, mean y, conic a, conic b, conic c, opacity, r, g, b, depth).
    """
    for i in prange(order.shape[0]):
        t = order[i]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        n = offsets[t + 1] - s
        gp, gf, sub_ids, sub_n = _gather_tile(means2d, conics, opacities, feats, flat_ids, s, n,
                                              tx * TILE, ty * TILE)
        # this tile's rows of v_isect: accumulated over its pixels, written once
        v = np.zeros((n, 10), np.float32)
        for py in range(TILE):
            y = ty * TILE + py
            if y >= height:
                break
            fy = np.float32(y)
            for px in range(TILE):
                x = tx * TILE + px
                if x >= width:
                    break
                walked = last[y, x]
                if walked == 0:
                    continue
                fx = np.float32(x)
                sb = (py // SUB) * NSUB + px // SUB
                T_final = final_T[y, x]
                T = T_final
                g_a = grad_alpha[y, x]
                buf0 = ZERO
                buf1 = ZERO
                buf2 = ZERO
                buf3 = ZERO
                go0 = grad_feats[y, x, 0]
                go1 = grad_feats[y, x, 1]
                go2 = grad_feats[y, x, 2]
                go3 = grad_feats[y, x, 3]
                for j in range(walked - 1, -1, -1):
                    k = sub_ids[sb, j]
                    dx = fx - gp[0, k]
                    dy = fy - gp[1, k]
                    a = gp[2, k]
                    b = gp[3, k]
                    c = gp[4, k]
                    sigma = HALF * (a * dx * dx + c * dy * dy) + b * dx * dy
                    if sigma < ZERO or sigma > gp[6, k]:
                        continue
                    vis = math.exp(-sigma)
                    o_vis = gp[5, k] * vis
                    alpha = min(ALPHA_MAX, o_vis)
                    if alpha < ALPHA_MIN:
                        continue
                    ra = ONE / (ONE - alpha)
                    T = T * ra  # transmittance in front of Gaussian k
                    fac = alpha * T
                    f0 = gf[k, 0]
                    f1 = gf[k, 1]
                    f2 = gf[k, 2]
                    f3 = gf[k, 3]
                    v[k, 6] += fac * go0
                    v[k, 7] += fac * go1
                    v[k, 8] += fac * go2
                    v[k, 9] += fac * go3
                    v_alpha = T_final * ra * g_a + (f0 * T - buf0 * ra) * go0 + (f1 * T - buf1 * ra) * go1 \
                        + (f2 * T - buf2 * ra) * go2 + (f3 * T - buf3 * ra) * go3
                    buf0 += f0 * fac
                    buf1 += f1 * fac
                    buf2 += f2 * fac
                    buf3 += f3 * fac
                    if o_vis <= ALPHA_MAX:  # the clamp passes no gradient
                        v_sigma = -o_vis * v_alpha
                        # d sigma / d mean = -(conic @ (pixel - mean))
                        v[k, 0] -= v_sigma * (a * dx + b * dy)
                        v[k, 1] -= v_sigma * (b * dx + c * dy)
                        v[k, 2] += HALF * v_sigma * dx * dx
                        v[k, 3] += v_sigma * dx * dy
                        v[k, 4] += HALF * v_sigma * dy * dy
                        v[k, 5] += vis * v_alpha
        for k in range(n):
            for j in range(10):
                v_isect[s + k, j] = v[k, j]


@_jit_serial
def bin_tiles_csr(means2d, radii, depths, tiles_x, tiles_y):
    """The reference's tile binning (:func:`..projection.bin_tiles`) as compressed lists.

    means2d [N, 2] float32, radii [N] int32 (0 = culled), depths [N] float32. Returns offsets [T + 1] and flat_ids [M]
    (int64): tile t's Gaussians, front to back (ties in depth by index, as the reference's stable sorts), are
    ``flat_ids[offsets[t]:offsets[t + 1]]``. The tile range of a Gaussian is computed with the reference's float32
    operations in the same order, so both produce identical lists.
    """
    n = radii.shape[0]
    n_tiles = tiles_x * tiles_y
    n_vis = 0
    for g in range(n):
        if radii[g] > 0:
            n_vis += 1
    vis = np.empty(n_vis, np.int64)
    vd = np.empty(n_vis, np.float32)
    j = 0
    for g in range(n):
        if radii[g] > 0:
            vis[j] = g
            vd[j] = depths[g]
            j += 1
    by_depth = vis[np.argsort(vd, kind="mergesort")]
    rect = np.empty((n_vis, 4), np.int64)
    counts = np.zeros(n_tiles + 1, np.int64)
    inv_tile = np.float32(1.0 / TILE)
    for i in range(n_vis):
        g = by_depth[i]
        r = np.float32(radii[g])
        mx = means2d[g, 0]
        my = means2d[g, 1]
        x0 = min(max(math.floor(((mx - r) + HALF) * inv_tile), 0), tiles_x)
        x1 = min(max(math.floor(((mx + r) + HALF) * inv_tile) + 1, 0), tiles_x)
        y0 = min(max(math.floor(((my - r) + HALF) * inv_tile), 0), tiles_y)
        y1 = min(max(math.floor(((my + r) + HALF) * inv_tile) + 1, 0), tiles_y)
        rect[i, 0] = x0
        rect[i, 1] = x1
        rect[i, 2] = y0
        rect[i, 3] = y1
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    flat_ids = np.empty(offsets[-1], np.int64)
    for i in range(n_vis):
        g = by_depth[i]
        for ty in range(rect[i, 2], rect[i, 3]):
            for tx in range(rect[i, 0], rect[i, 1]):
                t = ty * tiles_x + tx
                flat_ids[fill[t]] = g
                fill[t] += 1
    return offsets, flat_ids


def run(kernel, *args) -> None:
    """Call a kernel with chunks of one tile, so that idle cores take the next tile (dynamic load balance)."""
    old = numba.set_parallel_chunksize(1)
    try:
        kernel(*args)
    finally:
        numba.set_parallel_chunksize(old)
