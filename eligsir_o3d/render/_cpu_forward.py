"""Forward compositing kernel of the ``cpu`` renderer: every tile front to back, in pixel blocks of a chosen shape.

:func:`make` compiles the kernel for one block shape (bw x bh pixels); the shape is a compile-time constant of the
kernel (a closure variable, which numba treats as a constant and hashes into its cache key), so each shape is a
kernel of its own and the tests can run every shape the package may choose on any CPU (:mod:`._cpu_kernels`).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from ..runtime.jit import compile_kernel as _compile
from ..runtime.jit import full_width_vectors
from ._cpu_kernels import ALPHA_MIN, ONE, SOURCE_CRC, T_MIN, TILE, ZERO, conic_alpha, gather_tile


def make(bw: int, bh: int):
    """The forward kernel for blocks of bw x bh pixels (both divide the 16-pixel tile)."""
    NP = bw * bh
    NBX = TILE // bw
    NB = NBX * (TILE // bh)
    # Offsets of the per-pixel state in the block's scratch (one array, so that LLVM sees the rows cannot overlap
    # and vectorises the pixel loop without run-time overlap checks: 11-16 % off the kernel, the same bits):
    # pixel centre x, y; 1 while compositing (0: stopped or outside the image); transmittance; accumulated r, g, b,
    # depth; sum of weights; how far the pixel walked through the block's list (exact: lists are far shorter than
    # 2^24).
    LX, LY, LIVE, TR, A0, A1, A2, A3, WSUM, WALKED = (i * NP for i in range(10))
    crc = SOURCE_CRC  # the helpers' source, in the cache key (see _cpu_kernels.SOURCE_CRC)

    def composite_forward(means2d, conics, opacities, feats, bounds, offsets, flat_ids, order, slots, tiles_x, width,
                          height, out_feats, out_alpha, out_T, out_last, par, sub, sub_n):
        """Blend every tile front to back.

        means2d [N, 2], conics [N, 3], opacities [N], feats [N, 4] (r, g, b, depth), bounds [N, 3]
        (:func:`._cpu_kernels.cull_bounds`), all float32; offsets [T + 1] and flat_ids [M] (int64): tile t's
        depth-sorted Gaussians are ``flat_ids[offsets[t]:offsets[t + 1]]``; order [T]: the tiles to run, heaviest
        first, in ``slots`` parallel tasks (:func:`._cpu_kernels.task_slots`). Writes out_feats [H, W, 4]
        (accumulated features), out_alpha [H, W] (accumulated opacity), out_T [H, W] (final transmittance) and
        out_last [H, W] int32 (how far the pixel walked through its block's list), and the gathered tiles (par, sub,
        sub_n: :func:`._cpu_kernels.gather_shapes`) that the backward pass reads.

        The pixels of a block advance through the block's list together, branch-free (one SIMD batch); a pixel
        whose compositing has stopped is masked out, and the block stops when all its pixels have. Every
        per-pixel value is float32 (flags and counts too), and state is updated by arithmetic rather than by
        conditional stores, so the batch vectorises at the full float32 width of the target.
        """
        if crc < 0:  # never (a checksum is >= 0); it makes crc a closure constant of the kernel
            return
        for task in prange(slots):
            full_width_vectors()
            st = np.empty(10 * NP, np.float32)  # the block's per-pixel state, one array (below)
            for i in range(task, order.shape[0], slots):
                t = order[i]
                ty = t // tiles_x
                tx = t - ty * tiles_x
                s = offsets[t]
                gather_tile(means2d, conics, opacities, feats, bounds, flat_ids, s, offsets[t + 1] - s, tx * TILE,
                            ty * TILE, bw, bh, par, sub, sub_n, t)
                for sb in range(NB):
                    bx0 = tx * TILE + (sb % NBX) * bw
                    by0 = ty * TILE + (sb // NBX) * bh
                    n_live = 0
                    for p in range(NP):
                        x = bx0 + p % bw
                        y = by0 + p // bw
                        st[LX + p] = np.float32(x)
                        st[LY + p] = np.float32(y)
                        inside = x < width and y < height
                        st[LIVE + p] = ONE if inside else ZERO
                        n_live += 1 if inside else 0
                        st[TR + p] = ONE
                        st[A0 + p] = ZERO
                        st[A1 + p] = ZERO
                        st[A2 + p] = ZERO
                        st[A3 + p] = ZERO
                        st[WSUM + p] = ZERO
                        st[WALKED + p] = ZERO
                    if n_live == 0:
                        continue
                    first = NB * s + sb * (offsets[t + 1] - s)
                    for j in range(sub_n[t, sb]):
                        r = s + sub[first + j]
                        mx, my, ca, cb, cc = par[r, 0], par[r, 1], par[r, 2], par[r, 3], par[r, 4]
                        o, smax = par[r, 5], par[r, 6]
                        f0, f1, f2, f3 = par[r, 7], par[r, 8], par[r, 9], par[r, 10]
                        jf = np.float32(j + 1)
                        alive = False
                        for p in range(NP):
                            _, _, sigma, _, _, alpha = conic_alpha(st[LX + p], st[LY + p], mx, my, ca, cb, cc, o)
                            Tp = st[TR + p]
                            next_T = Tp * (ONE - alpha)
                            use = (st[LIVE + p] > ZERO) & (sigma >= ZERO) & (sigma <= smax) & (alpha >= ALPHA_MIN)
                            stop = use & (next_T <= T_MIN)  # this Gaussian is not blended, and nothing after it
                            blend = use & (next_T > T_MIN)
                            ab = alpha if blend else ZERO
                            w = ab * Tp
                            st[A0 + p] += w * f0
                            st[A1 + p] += w * f1
                            st[A2 + p] += w * f2
                            st[A3 + p] += w * f3
                            st[WSUM + p] += w
                            st[TR + p] = Tp * (ONE - ab)  # = next_T where blended, Tp (exactly) where not
                            # = jf where blended, else unchanged (exact: integers below 2^24); arithmetic, not max() or
                            # a select, which LLVM turns into a masked store
                            wp = st[WALKED + p]
                            st[WALKED + p] = wp + (jf - wp) * (ONE if blend else ZERO)
                            lp = st[LIVE + p] - (ONE if stop else ZERO)  # stop implies live = 1
                            st[LIVE + p] = lp
                            alive = alive | (lp > ZERO)
                        if not alive:
                            break
                    for p in range(NP):
                        x = bx0 + p % bw
                        y = by0 + p // bw
                        if x < width and y < height:
                            out_feats[y, x, 0] = st[A0 + p]
                            out_feats[y, x, 1] = st[A1 + p]
                            out_feats[y, x, 2] = st[A2 + p]
                            out_feats[y, x, 3] = st[A3 + p]
                            out_alpha[y, x] = st[WSUM + p]  # = 1 - T up to rounding; summed like the reference
                            out_T[y, x] = st[TR + p]
                            out_last[y, x] = np.int32(st[WALKED + p])

    return _compile(parallel=True)(composite_forward)
