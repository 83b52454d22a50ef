"""Backward compositing kernel of the ``cpu`` renderer: the gradient of :mod:`._cpu_forward`, back to front.

:func:`make` compiles it for one block shape (bw x bh pixels), a compile-time constant as in :mod:`._cpu_forward`;
the forward and backward kernels of a render must use the same shape (the forward's walk counts are per block list).
A block's per-Gaussian gradients (:data:`CHANNELS` rows of its pixels) are summed over the pixels by
:func:`add_pixel_sums`, vector shuffles and adds that LLVM emits for the target's width, in the same pairwise order
on every target.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import prange, types
from numba.extending import intrinsic

from ..runtime.jit import compile_kernel as _compile
from ..runtime.jit import full_width_vectors
from ._cpu_kernels import (ALPHA_MAX, ALPHA_MIN, HALF, ISECT_COLS, ONE, SOURCE_CRC, TILE, ZERO, conic_alpha,
                           reaches)

CHANNELS = 10  # gradient channels per intersection: mean x, y, conic a, b, c, opacity, 4 features
assert CHANNELS <= ISECT_COLS == 16


def _pair_halves(builder, x, y, h):
    """Lanes of x then y in groups of 2h, each group's first h lanes plus its last h: ``z[g h + q] = w[2 g h + q] +
    w[2 g h + q + h]`` over the concatenation w of x and y (16 lanes each), the same additions as a scalar
    ``a[q] += a[q + h]`` over every group."""
    lo = [g * 2 * h + q for g in range(16 // h) for q in range(h)]
    hi = [i + h for i in lo]
    i32 = ir.IntType(32)
    mask = [ir.Constant(ir.VectorType(i32, 16), [ir.Constant(i32, i) for i in m]) for m in (lo, hi)]
    return builder.fadd(builder.shuffle_vector(x, y, mask[0]), builder.shuffle_vector(x, y, mask[1]))


@intrinsic
def add_pixel_sums(typingctx, st, first, v_isect, row):
    """v_isect[row, c] += the sum of dv[c, 0:16] for the CHANNELS rows of dv = st[first:first + 16 CHANNELS] as
    [CHANNELS, 16] (st 1-D float32, first a multiple of 16), v_isect [M, 16] C-ordered (columns CHANNELS.. are
    scratch). The sums run in the pairwise order 16 -> 8 -> 4 -> 2 -> 1
    (``dv[c, p] + dv[c, p + 8]``, then ``+ 4``, ``+ 2``, then lanes 0 + 1), written as vector shuffles and adds so
    that the sums of all rows run side by side in whole registers (summed row by row in scalar code, they were the
    kernel's largest part). Lane for lane these are the additions of the scalar order, so the bits do not depend on the
    target's vector width."""
    sig = types.void(st, first, v_isect, row)

    def codegen(context, builder, signature, args):
        v16 = ir.VectorType(ir.FloatType(), 16)
        src = context.make_array(signature.args[0])(context, builder, args[0]).data
        dst = context.make_array(signature.args[2])(context, builder, args[2]).data
        base = builder.gep(src, [args[1]], source_etype=ir.FloatType())
        base = builder.bitcast(base, v16.as_pointer())
        rows = [builder.load(builder.gep(base, [ir.Constant(ir.IntType(64), c)], source_etype=v16), typ=v16,
                             align=4) for c in range(CHANNELS)]
        h = 8
        while h >= 1:  # each step halves the partial sums per channel and packs twice the channels per register
            rows = [_pair_halves(builder, rows[i], rows[min(i + 1, len(rows) - 1)], h) for i in range(0, len(rows), 2)]
            h //= 2
        at = builder.gep(builder.bitcast(dst, v16.as_pointer()), [args[3]], source_etype=v16)
        builder.store(builder.fadd(builder.load(at, typ=v16, align=4), rows[0]), at, align=4)
        return context.get_dummy_value()
    return sig, codegen

def make(bw: int, bh: int):
    """The backward kernel for blocks of bw x bh pixels (both divide the 16-pixel tile)."""
    NP = bw * bh
    NBX = TILE // bw
    NB = NBX * (TILE // bh)
    if NP != 16:
        raise ValueError(f"the backward kernel's pixel sum is written for 16-pixel blocks, not {bw}x{bh}")
    # Offsets of the per-pixel state in the block's scratch (one array, so that LLVM sees the rows cannot overlap, as
    # in the forward kernel): pixel centre x, y; how far the forward walked; transmittance; final transmittance;
    # gradients of alpha and the 4 features; running sums of the features behind; then the CHANNELS gradient rows.
    LX, LY, WALKED, TR, TFIN, GA, G0, G1, G2, G3, B0, B1, B2, B3, DV = (i * NP for i in range(15))
    STATE = 14 + CHANNELS
    crc = SOURCE_CRC  # the helpers' source, in the cache key (see _cpu_kernels.SOURCE_CRC)

    def composite_backward(par, sub, sub_n, offsets, flat_ids, order, slots, tiles_x, width, height, final_T, last,
                           grad_feats, grad_alpha, v_isect, v):
        """Back-to-front gradients of the forward kernel, on the tiles it gathered (par, sub, sub_n).

        grad_feats [H, W, 4], grad_alpha [H, W]: gradients of the accumulated outputs. Writes v_isect [M, ISECT_COLS],
        one row per intersection: d/d(mean x, mean y, conic a, conic b, conic c, opacity, r, g, b, depth), then
        scratch columns, and the sums of those 10 per Gaussian into v [N, 10] (after the tiles, in intersection order:
        deterministic).

        Per pixel this is gsplat's backward: start from the final transmittance, walk the blended Gaussians back to
        front, recover each one's transmittance as ``T / (1 - alpha)`` and keep the running sums of what lies
        behind. The pixels of a block run as one branch-free SIMD batch (float32 throughout, no conditional
        stores); their per-Gaussian gradients are summed in a fixed pairwise order.
        """
        if crc < 0:  # never (a checksum is >= 0); it makes crc a closure constant of the kernel
            return
        if v_isect.shape[1] != ISECT_COLS or not v_isect.flags.c_contiguous:
            raise ValueError("v_isect must be a C-ordered [M, ISECT_COLS] array")
        for task in prange(slots):
            full_width_vectors()
            st = np.empty(STATE * NP, np.float32)  # the block's per-pixel state and gradient rows, one array (below)
            for i in range(task, order.shape[0], slots):
                t = order[i]
                ty = t // tiles_x
                tx = t - ty * tiles_x
                s = offsets[t]
                n = offsets[t + 1] - s
                for k in range(n):  # this tile's rows (indexed, not a view: see gather_tile)
                    for c in range(ISECT_COLS):
                        v_isect[s + k, c] = ZERO
                for sb in range(NB):
                    bx0 = tx * TILE + (sb % NBX) * bw
                    by0 = ty * TILE + (sb // NBX) * bh
                    j_end = 0
                    for p in range(NP):
                        x = bx0 + p % bw
                        y = by0 + p // bw
                        st[LX + p] = np.float32(x)
                        st[LY + p] = np.float32(y)
                        st[B0 + p] = ZERO
                        st[B1 + p] = ZERO
                        st[B2 + p] = ZERO
                        st[B3 + p] = ZERO
                        if x < width and y < height:
                            j_end = max(j_end, last[y, x])
                            st[WALKED + p] = np.float32(last[y, x])
                            st[TR + p] = final_T[y, x]
                            st[GA + p] = grad_alpha[y, x]
                            st[G0 + p] = grad_feats[y, x, 0]
                            st[G1 + p] = grad_feats[y, x, 1]
                            st[G2 + p] = grad_feats[y, x, 2]
                            st[G3 + p] = grad_feats[y, x, 3]
                        else:
                            st[WALKED + p] = ZERO
                            st[TR + p] = ONE
                            st[GA + p] = ZERO
                            st[G0 + p] = ZERO
                            st[G1 + p] = ZERO
                            st[G2 + p] = ZERO
                            st[G3 + p] = ZERO
                        st[TFIN + p] = st[TR + p]
                    first = NB * s + sb * n
                    for j in range(j_end - 1, -1, -1):
                        k = sub[first + j]
                        r = s + k
                        mx, my, ca, cb, cc = par[r, 0], par[r, 1], par[r, 2], par[r, 3], par[r, 4]
                        o, smax = par[r, 5], par[r, 6]
                        f0, f1, f2, f3 = par[r, 7], par[r, 8], par[r, 9], par[r, 10]
                        jf = np.float32(j)
                        # a cheap pass without exp first, for the Gaussians of the list that miss all the block's pixels
                        # (3-9% of the backward on the benchmark scene; the same pass costs the forward 2-10%)
                        hit = False
                        for p in range(NP):
                            hit = hit | ((jf < st[WALKED + p]) & reaches(st[LX + p], st[LY + p], mx, my, ca, cb, cc,
                                                                          smax))
                        if not hit:
                            continue
                        any_use = False
                        for p in range(NP):
                            dx, dy, sigma, vis, o_vis, alpha = conic_alpha(st[LX + p], st[LY + p], mx, my, ca, cb, cc,
                                                                           o)
                            use = (jf < st[WALKED + p]) & (sigma >= ZERO) & (sigma <= smax) & (alpha >= ALPHA_MIN)
                            ra = ONE / (ONE - alpha)
                            Tp = st[TR + p]
                            Tk = Tp * ra  # transmittance in front of Gaussian k
                            fac = alpha * Tk
                            g0, g1, g2, g3 = st[G0 + p], st[G1 + p], st[G2 + p], st[G3 + p]
                            v_alpha = st[TFIN + p] * ra * st[GA + p] + (f0 * Tk - st[B0 + p] * ra) * g0 \
                                + (f1 * Tk - st[B1 + p] * ra) * g1 + (f2 * Tk - st[B2 + p] * ra) * g2 \
                                + (f3 * Tk - st[B3 + p] * ra) * g3
                            # the alpha clamp passes no gradient to opacity and sigma
                            v_sigma = -o_vis * v_alpha if use & (o_vis <= ALPHA_MAX) else ZERO
                            # d sigma / d mean = -(conic @ (pixel - mean))
                            st[DV + p] = -v_sigma * (ca * dx + cb * dy)
                            st[DV + NP + p] = -v_sigma * (cb * dx + cc * dy)
                            st[DV + 2 * NP + p] = HALF * v_sigma * dx * dx
                            st[DV + 3 * NP + p] = v_sigma * dx * dy
                            st[DV + 4 * NP + p] = HALF * v_sigma * dy * dy
                            st[DV + 5 * NP + p] = vis * v_alpha if use & (o_vis <= ALPHA_MAX) else ZERO
                            fac = fac if use else ZERO
                            st[DV + 6 * NP + p] = fac * g0
                            st[DV + 7 * NP + p] = fac * g1
                            st[DV + 8 * NP + p] = fac * g2
                            st[DV + 9 * NP + p] = fac * g3
                            st[B0 + p] += f0 * fac
                            st[B1 + p] += f1 * fac
                            st[B2 + p] += f2 * fac
                            st[B3 + p] += f3 * fac
                            st[TR + p] = Tp * (ra if use else ONE)  # = Tk where used, Tp (exactly) where not
                            any_use = any_use | use
                        if not any_use:  # most of a block's list misses most of its pixels
                            continue
                        add_pixel_sums(st, DV, v_isect, s + k)  # pairwise over the block's pixels
        v[:] = ZERO
        for i in range(flat_ids.shape[0]):
            g = flat_ids[i]
            for c in range(CHANNELS):
                v[g, c] += v_isect[i, c]

    return _compile(parallel=True)(composite_backward)
