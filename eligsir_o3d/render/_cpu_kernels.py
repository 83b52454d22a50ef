"""Numba kernels of the ``cpu`` renderer: per-tile front-to-back compositing and its back-to-front gradient.

The math is the reference's (``torch_backend.TorchRenderer._tiles``) written per pixel, in float32, in the same
order of operations: ``sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy`` with ``(dx, dy) = pixel - mean``, Gaussians with
``sigma < 0`` or ``alpha < 1/255`` are skipped, ``alpha = min(0.999, o exp(-sigma))``, and a pixel stops before the
Gaussian whose blending would take its transmittance to ``<= 1e-4``. The backward pass follows gsplat's
``rasterize_to_pixels`` backward: it starts from the stored final transmittance and the number of Gaussians the
forward pass walked through, and recovers each Gaussian's transmittance by dividing by ``1 - alpha``.

Work: pixels run in 4x4 blocks, and a block walks only the part of its tile's list that can reach it: each tile's
list is culled per block by the bounding box of the ellipse where ``o exp(-sigma) >= 1/255`` (conservatively, so
the result is the same as walking the whole list; on a real scene this cuts the walk from ~540 to ~80 Gaussians per
pixel at 160x120). The 16 pixels of a block are processed together without branches, which LLVM turns into SIMD
code; exp is a branch-free polynomial within 2 ulp of float32 exp (the reference's exp differs from it by rounding
only, so images agree to ~1e-6).

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


SUB = 4  # pixel blocks of SUB x SUB: one SIMD batch of pixels, each with its own culled Gaussian list
NSUB = TILE // SUB
NP = SUB * SUB

# exp(-s), float32, branch-free so that loops over a block's 16 pixels vectorise: s = n ln2 + r (Cody-Waite),
# exp(-r) by its degree-9 Taylor polynomial on [0, ln2) (truncation < 1e-8), 2^-n by selects. Within 2 ulp of
# float32 exp over [0, 16]; beyond 16 (alpha below 1/255 for any opacity up to 3e4) the value is not used.
SIG_CLAMP = np.float32(16.0)
LOG2E = np.float32(1.4426950408889634)
LN2_HI = np.float32(0.693145751953125)
LN2_LO = np.float32(1.4286068203094173e-06)
E0, E1, E2, E3, E4, E5, E6, E7, E8, E9 = (np.float32((-1.0) ** i / math.factorial(i)) for i in range(10))


@numba.njit(inline="always", fastmath=False)
def exp_neg(s):
    s = min(max(s, ZERO), SIG_CLAMP)
    n = np.int32(s * LOG2E)  # floor: s >= 0
    fn = np.float32(n)
    r = (s - fn * LN2_HI) - fn * LN2_LO
    p = ((((((((E9 * r + E8) * r + E7) * r + E6) * r + E5) * r + E4) * r + E3) * r + E2) * r + E1) * r + E0
    p = p * (np.float32(0.5) if n & 1 else ONE)
    p = p * (np.float32(0.25) if n & 2 else ONE)
    p = p * (np.float32(2.0 ** -4) if n & 4 else ONE)
    p = p * (np.float32(2.0 ** -8) if n & 8 else ONE)
    return p * (np.float32(2.0 ** -16) if n & 16 else ONE)


@_jit
def cull_bounds(conics, opacities, out):
    """Per Gaussian: out[g] = (sigma bound, x half-width, y half-width) of the region it can reach.

    A Gaussian contributes to a pixel only if ``o exp(-sigma) >= 1/255``, i.e. ``sigma <= log(255 o)``; the bound
    keeps a margin of 1e-3 above that (float32 exp and products err by ~1e-7; -1 where ``o < 1/255``: never). The
    half-widths bound the ellipse at that level, widened for the float32 rounding of sigma in the kernels, which
    grows with the conic's condition (at most ~1e-6 * kappa * sigma with kappa = (a + c)^2 / det: ~4 for round
    Gaussians, 1e5 for 300:1 needles), and by 1e-3 px; -1 = no box (degenerate conic or NaN: never culled).
    Culling is conservative, so it changes no result.
    """
    for g in prange(opacities.shape[0]):
        o = np.float64(opacities[g])
        out[g, 1] = -1.0
        out[g, 2] = -1.0
        if o != o:  # NaN: leave it to the per-pixel tests
            out[g, 0] = np.inf
            continue
        if o * 255.0 < 1.0:
            out[g, 0] = -1.0
            continue
        smax = math.log(o * 255.0) + 1e-3
        out[g, 0] = smax
        a, b, c = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        det = a * c - b * b
        if det > 0.0 and a > 0.0:
            s_box = smax * (1.0 + 1e-3 + 2e-6 * (a + c) * (a + c) / det)
            out[g, 1] = math.sqrt(2.0 * s_box * c / det) + 1e-3
            out[g, 2] = math.sqrt(2.0 * s_box * a / det) + 1e-3


@_jit_serial
def _gather_tile(means2d, conics, opacities, feats, bounds, flat_ids, s, n, x0, y0):
    """Copy tile Gaussians ``flat_ids[s:s + n]`` into contiguous arrays and cull them per pixel block.

    Returns gp [7, n] (mean x, mean y, conic a, b, c, opacity, sigma bound), gf [n, 4] and, per block, the
    depth-ordered local indices of the Gaussians whose box (:func:`cull_bounds`) reaches it: sub_ids [NSUB^2, n],
    sub_n [NSUB^2].
    """
    gp = np.empty((7, n), np.float32)
    gf = np.empty((n, 4), np.float32)
    sub_ids = np.empty((NSUB * NSUB, n), np.int32)
    sub_n = np.zeros(NSUB * NSUB, np.int64)
    for k in range(n):
        g = flat_ids[s + k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        gp[0, k] = mx
        gp[1, k] = my
        gp[2, k] = conics[g, 0]
        gp[3, k] = conics[g, 1]
        gp[4, k] = conics[g, 2]
        gp[5, k] = opacities[g]
        gp[6, k] = bounds[g, 0]
        for f in range(4):
            gf[k, f] = feats[g, f]
        if bounds[g, 0] < 0.0:
            continue
        rx = np.float64(bounds[g, 1])
        ry = np.float64(bounds[g, 2])
        sx0, sx1, sy0, sy1 = 0, NSUB - 1, 0, NSUB - 1
        if rx >= 0.0:
            # block j spans pixel centres [x0 + SUB j, x0 + SUB j + SUB - 1]
            lo_x = (np.float64(mx) - rx - x0) / SUB
            hi_x = (np.float64(mx) + rx - x0) / SUB
            lo_y = (np.float64(my) - ry - y0) / SUB
            hi_y = (np.float64(my) + ry - y0) / SUB
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
def composite_forward(means2d, conics, opacities, feats, bounds, offsets, flat_ids, order, tiles_x, width, height,
                      out_feats, out_alpha, out_T, out_last):
    """Blend every tile front to back.

    means2d [N, 2], conics [N, 3], opacities [N], feats [N, 4] (r, g, b, depth), bounds [N, 3] (:func:`cull_bounds`),
    all float32; offsets [T + 1] and flat_ids [M] (int64): tile t's depth-sorted Gaussians are
    ``flat_ids[offsets[t]:offsets[t + 1]]``; order [T]: the tiles to run, heaviest first. Writes out_feats [H, W, 4]
    (accumulated features), out_alpha [H, W] (accumulated opacity), out_T [H, W] (final transmittance) and out_last
    [H, W] int32 (how far the pixel walked through its block's list).

    The 16 pixels of a block advance through the block's list together, branch-free (one SIMD batch); a pixel
    whose compositing has stopped is masked out, and the block stops when all its pixels have.
    """
    for i in prange(order.shape[0]):
        t = order[i]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        gp, gf, sub_ids, sub_n = _gather_tile(means2d, conics, opacities, feats, bounds, flat_ids, s,
                                              offsets[t + 1] - s, tx * TILE, ty * TILE)
        lx = np.empty(NP, np.float32)
        ly = np.empty(NP, np.float32)
        live = np.empty(NP, np.bool_)
        T = np.empty(NP, np.float32)
        a0 = np.empty(NP, np.float32)
        a1 = np.empty(NP, np.float32)
        a2 = np.empty(NP, np.float32)
        a3 = np.empty(NP, np.float32)
        wsum = np.empty(NP, np.float32)
        walked = np.empty(NP, np.int32)
        for sb in range(NSUB * NSUB):
            bx0 = tx * TILE + (sb % NSUB) * SUB
            by0 = ty * TILE + (sb // NSUB) * SUB
            n_live = 0
            for p in range(NP):
                x = bx0 + p % SUB
                y = by0 + p // SUB
                lx[p] = np.float32(x)
                ly[p] = np.float32(y)
                live[p] = x < width and y < height
                n_live += 1 if live[p] else 0
                T[p] = ONE
                a0[p] = ZERO
                a1[p] = ZERO
                a2[p] = ZERO
                a3[p] = ZERO
                wsum[p] = ZERO
                walked[p] = 0
            if n_live == 0:
                continue
            for j in range(sub_n[sb]):
                k = sub_ids[sb, j]
                mx, my, ca, cb, cc = gp[0, k], gp[1, k], gp[2, k], gp[3, k], gp[4, k]
                o, smax = gp[5, k], gp[6, k]
                f0, f1, f2, f3 = gf[k, 0], gf[k, 1], gf[k, 2], gf[k, 3]
                stopped = 0
                for p in range(NP):
                    dx = lx[p] - mx
                    dy = ly[p] - my
                    sigma = HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    alpha = min(ALPHA_MAX, o * exp_neg(sigma))
                    Tp = T[p]
                    next_T = Tp * (ONE - alpha)
                    use = live[p] & (sigma >= ZERO) & (sigma <= smax) & (alpha >= ALPHA_MIN)
                    stop = use & (next_T <= T_MIN)  # this Gaussian is not blended, and nothing after it
                    blend = use & (next_T > T_MIN)
                    w = alpha * Tp if blend else ZERO
                    a0[p] += w * f0
                    a1[p] += w * f1
                    a2[p] += w * f2
                    a3[p] += w * f3
                    wsum[p] += w
                    T[p] = next_T if blend else Tp
                    walked[p] = np.int32(j + 1) if blend else walked[p]
                    live[p] = live[p] & ~stop
                    stopped += 1 if stop else 0
                n_live -= stopped
                if n_live == 0:
                    break
            for p in range(NP):
                x = bx0 + p % SUB
                y = by0 + p // SUB
                if x < width and y < height:
                    out_feats[y, x, 0] = a0[p]
                    out_feats[y, x, 1] = a1[p]
                    out_feats[y, x, 2] = a2[p]
                    out_feats[y, x, 3] = a3[p]
                    out_alpha[y, x] = wsum[p]  # = 1 - T up to rounding; summed like the reference
                    out_T[y, x] = T[p]
                    out_last[y, x] = walked[p]


@_jit
def composite_backward(means2d, conics, opacities, feats, bounds, offsets, flat_ids, order, tiles_x, width, height,
                       final_T, last, grad_feats, grad_alpha, v_isect):
    """Back-to-front gradients of ``composite_forward``.

    grad_feats [H, W, 4], grad_alpha [H, W]: gradients of the accumulated outputs. Writes v_isect [M, 10], one row
    per intersection: d/d(mean x, mean y, conic a, conic b, conic c, opacity, r, g, b, depth).

    Per pixel this is gsplat's backward: start from the final transmittance, walk the blended Gaussians back to
    front, recover each one's transmittance as ``T / (1 - alpha)`` and keep the running sums of what lies behind.
    The 16 pixels of a block run as one branch-free SIMD batch; their per-Gaussian gradients are summed in a fixed
    pairwise order (so the result does not depend on the vector width).
    """
    for i in prange(order.shape[0]):
        t = order[i]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        n = offsets[t + 1] - s
        gp, gf, sub_ids, sub_n = _gather_tile(means2d, conics, opacities, feats, bounds, flat_ids, s, n,
                                              tx * TILE, ty * TILE)
        v = np.zeros((n, 10), np.float32)  # this tile's rows of v_isect, written once at the end
        lx = np.empty(NP, np.float32)
        ly = np.empty(NP, np.float32)
        walked = np.empty(NP, np.int32)
        T = np.empty(NP, np.float32)
        T_final = np.empty(NP, np.float32)
        g_a = np.empty(NP, np.float32)
        g0 = np.empty(NP, np.float32)
        g1 = np.empty(NP, np.float32)
        g2 = np.empty(NP, np.float32)
        g3 = np.empty(NP, np.float32)
        b0 = np.empty(NP, np.float32)
        b1 = np.empty(NP, np.float32)
        b2 = np.empty(NP, np.float32)
        b3 = np.empty(NP, np.float32)
        dv = np.empty((10, NP), np.float32)
        for sb in range(NSUB * NSUB):
            bx0 = tx * TILE + (sb % NSUB) * SUB
            by0 = ty * TILE + (sb // NSUB) * SUB
            j_end = 0
            for p in range(NP):
                x = bx0 + p % SUB
                y = by0 + p // SUB
                lx[p] = np.float32(x)
                ly[p] = np.float32(y)
                b0[p] = ZERO
                b1[p] = ZERO
                b2[p] = ZERO
                b3[p] = ZERO
                if x < width and y < height:
                    walked[p] = last[y, x]
                    T[p] = final_T[y, x]
                    g_a[p] = grad_alpha[y, x]
                    g0[p] = grad_feats[y, x, 0]
                    g1[p] = grad_feats[y, x, 1]
                    g2[p] = grad_feats[y, x, 2]
                    g3[p] = grad_feats[y, x, 3]
                else:
                    walked[p] = 0
                    T[p] = ONE
                    g_a[p] = ZERO
                    g0[p] = ZERO
                    g1[p] = ZERO
                    g2[p] = ZERO
                    g3[p] = ZERO
                T_final[p] = T[p]
                j_end = max(j_end, walked[p])
            for j in range(j_end - 1, -1, -1):
                k = sub_ids[sb, j]
                mx, my, ca, cb, cc = gp[0, k], gp[1, k], gp[2, k], gp[3, k], gp[4, k]
                o, smax = gp[5, k], gp[6, k]
                f0, f1, f2, f3 = gf[k, 0], gf[k, 1], gf[k, 2], gf[k, 3]
                n_use = 0
                for p in range(NP):
                    dx = lx[p] - mx
                    dy = ly[p] - my
                    sigma = HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    vis = exp_neg(sigma)
                    o_vis = o * vis
                    alpha = min(ALPHA_MAX, o_vis)
                    use = (j < walked[p]) & (sigma >= ZERO) & (sigma <= smax) & (alpha >= ALPHA_MIN)
                    ra = ONE / (ONE - alpha)
                    Tk = T[p] * ra  # transmittance in front of Gaussian k
                    fac = alpha * Tk
                    v_alpha = T_final[p] * ra * g_a[p] + (f0 * Tk - b0[p] * ra) * g0[p] \
                        + (f1 * Tk - b1[p] * ra) * g1[p] + (f2 * Tk - b2[p] * ra) * g2[p] \
                        + (f3 * Tk - b3[p] * ra) * g3[p]
                    # the alpha clamp passes no gradient to opacity and sigma
                    v_sigma = -o_vis * v_alpha if use & (o_vis <= ALPHA_MAX) else ZERO
                    # d sigma / d mean = -(conic @ (pixel - mean))
                    dv[0, p] = -v_sigma * (ca * dx + cb * dy)
                    dv[1, p] = -v_sigma * (cb * dx + cc * dy)
                    dv[2, p] = HALF * v_sigma * dx * dx
                    dv[3, p] = v_sigma * dx * dy
                    dv[4, p] = HALF * v_sigma * dy * dy
                    dv[5, p] = vis * v_alpha if use & (o_vis <= ALPHA_MAX) else ZERO
                    fac = fac if use else ZERO
                    dv[6, p] = fac * g0[p]
                    dv[7, p] = fac * g1[p]
                    dv[8, p] = fac * g2[p]
                    dv[9, p] = fac * g3[p]
                    b0[p] += f0 * fac
                    b1[p] += f1 * fac
                    b2[p] += f2 * fac
                    b3[p] += f3 * fac
                    T[p] = Tk if use else T[p]
                    n_use += 1 if use else 0
                if n_use == 0:  # most of a block's list misses most of its pixels
                    continue
                # pairwise sum over the block's pixels: 16 -> 8 -> 4 -> 2 -> 1
                h = NP // 2
                while h > 0:
                    for c in range(10):
                        for p in range(h):
                            dv[c, p] += dv[c, p + h]
                    h //= 2
                for c in range(10):
                    v[k, c] += dv[c, 0]
        for k in range(n):
            for c in range(10):
                v_isect[s + k, c] = v[k, c]


@_jit_serial
def bin_tiles_fill(means2d, radii, by_depth, tiles_x, tiles_y):
    """The reference's tile binning (:func:`..projection.bin_tiles`) as compressed lists.

    means2d [N, 2] float32, radii [N] int32, by_depth [V] int64: the visible Gaussians (radius > 0) front to back,
    ties in depth by index (the order of the reference's stable sorts). Returns offsets [T + 1] and flat_ids [M]
    (int64): tile t's Gaussians, front to back, are ``flat_ids[offsets[t]:offsets[t + 1]]``. The tile range of a
    Gaussian is computed with the reference's float32 operations in the same order, so the lists are identical.
    """
    n_vis = by_depth.shape[0]
    n_tiles = tiles_x * tiles_y
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
