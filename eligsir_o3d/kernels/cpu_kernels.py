"""Numba kernels of the ``numba`` kernel set: the view's rows gathered and activated in one pass, and the whole
step of those rows in one pass, written in place on the map.

- :func:`gather_activated`: the rows ``rows`` of the raw parameters as the renderer takes them (means, raw
  quaternions, scales in metres, opacities in (0, 1), colours: ``clamp_min(sh0 C0 + 0.5, 0)`` at degree 0, else
  sh0 and shN side by side);
- :func:`step_view`: per row, the chain rule from the activated leaves' gradients to the raw parameters, the
  MCMC regulariser's gradient, torch's Adam (float32, exact bias correction) of every stepped parameter and the
  position noise on the updated row (:func:`..optim.update_kernels.move_mean`), the formulas of
  :func:`.device_reference.step_rows`. Rows outside ``rows`` are neither read nor written.

Both run their rows in parallel (distinct rows write disjoint memory); their activations are
:mod:`..runtime.fmath`'s, so the bits do not depend on how a loop is vectorised or split over threads. Compiled
lazily on first use and cached on disk like the renderer's kernels (:mod:`..runtime.jit`).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from ..optim.update_kernels import mean_delta, noise_gate
from ..runtime.fmath import exp32, sigmoid32
from ..runtime.jit import full_width_vectors
from ..runtime.jit import jit as _jit
from .device_reference import C0

HYPER = 6  # per stepped parameter: (a, b, 1 - beta1, beta2, 1 - beta2, eps), as base.adam_factors gives them
MEANS, QUATS, SCALES, OPACITIES, SH0, SHN = range(6)  # the rows of ``hyper`` and ``has`` in step_view
LANES = 16  # rows gathered or stepped side by side


@_jit
def gather_activated(ps, rows, deg0, o_means, o_quats, o_scales, o_opac, o_colors):
    """Rows ``rows`` [M] of the raw map (``ps``: flat means, quats, log scales, logits, sh0, shN as in
    :func:`step_view`) into o_means [M, 3], o_quats [M, 4], o_scales [M, 3] (exp), o_opac [M] (sigmoid) and
    o_colors: [M, 3] RGB with ``deg0``, else [M, 3 + W] (sh0 then shN, the rows of a [M, K + 1, 3] tensor).
    The activations run :data:`LANES` rows side by side (a scratch column per row, one lane loop)."""
    pm, pq, ps_, po, p0, pn = ps
    c0, half, zero = np.float32(C0), np.float32(0.5), np.float32(0.0)
    wn = o_colors.shape[1] - 3
    n = rows.shape[0]
    for bi in prange((n + LANES - 1) // LANES):
        full_width_vectors()
        st = np.empty((4, LANES), np.float32)  # log scales, logit
        base = bi * LANES
        count = min(LANES, n - base)
        for lane in range(LANES):  # the last group repeats its last row in the spare lanes
            i = base + min(lane, count - 1)
            g = rows[i]
            for j in range(3):
                st[j, lane] = ps_[3 * g + j]
            st[3, lane] = po[g]
        for lane in range(LANES):
            for j in range(3):
                st[j, lane] = exp32(st[j, lane])
            st[3, lane] = sigmoid32(st[3, lane])
        for lane in range(count):
            i = base + lane
            g = rows[i]
            for j in range(3):
                o_means[i, j] = pm[3 * g + j]
                o_scales[i, j] = st[j, lane]
            for j in range(4):
                o_quats[i, j] = pq[4 * g + j]
            o_opac[i] = st[3, lane]
            if deg0:
                for c in range(3):
                    o_colors[i, c] = max(p0[3 * g + c] * c0 + half, zero)
            else:
                for c in range(3):
                    o_colors[i, c] = p0[3 * g + c]
                for j in range(wn):
                    o_colors[i, 3 + j] = pn[wn * g + j]


@numba.njit(inline="always", fastmath=False)
def _hyper(hyper, t):
    """Parameter t's Adam factors as float32 values: (a, b, 1 - beta1, beta2, 1 - beta2, eps)."""
    return (np.float32(hyper[t, 0]), np.float32(hyper[t, 1]), np.float32(hyper[t, 2]), np.float32(hyper[t, 3]),
            np.float32(hyper[t, 4]), np.float32(hyper[t, 5]))


@numba.njit(inline="always", fastmath=False)
def _adam_value(p, m, v, grad, h):
    """torch's Adam on one float32 element with factors h (:func:`_hyper`): the new (p, m, v)."""
    mi = m + h[2] * (grad - m)
    vi = v * h[3] + h[4] * grad * grad
    return p + h[0] * (mi / (np.sqrt(vi) / h[1] + h[5])), mi, vi


@numba.njit(inline="always", fastmath=False)
def _adam(p, m, v, k, grad, h):
    """:func:`_adam_value` on element k of parameter p (moments m, v), in place."""
    p[k], m[k], v[k] = _adam_value(p[k], m[k], v[k], grad, h)


# step_view's scratch: per stepped column (means 3, quats 4, scales 3, opacity 1, sh0 3: 14) four rows (parameter,
# moment 1, moment 2, gradient), then the noise's normal triple
COLS = (0, 3, 7, 10, 11, 14)  # first column of means, quats, scales, opacities, sh0; the total
PAR, M1, M2, GRAD, Z = 0, 14, 28, 42, 56


@numba.njit(inline="always", fastmath=False)
def _gather_lane(st, lane, i, g, t, flat, m, v, grads, width, has):
    """Column block t of scratch lane ``lane`` from row g of parameter ``flat`` (its moments m, v) and row i of
    its gradient [M, width] (zeros where the parameter is not stepped)."""
    for j in range(width):
        c = COLS[t] + j
        st[PAR + c, lane] = flat[width * g + j]
        st[M1 + c, lane] = m[width * g + j] if has else np.float32(0.0)
        st[M2 + c, lane] = v[width * g + j] if has else np.float32(0.0)
        st[GRAD + c, lane] = grads[i, j] if has else np.float32(0.0)


@numba.njit(inline="always", fastmath=False)
def _scatter_lane(st, lane, g, t, flat, m, v, width):
    """Column block t of scratch lane ``lane`` back to row g of parameter ``flat`` and its moments m, v."""
    for j in range(width):
        c = COLS[t] + j
        flat[width * g + j] = st[PAR + c, lane]
        m[width * g + j] = st[M1 + c, lane]
        v[width * g + j] = st[M2 + c, lane]


@numba.njit(inline="always", fastmath=False)
def _step_lane(st, lane, t, width, has, h):
    """Adam of column block t in one lane from its gradient row; the parameter moves only where it is stepped."""
    for j in range(width):
        c = COLS[t] + j
        p, mi, vi = _adam_value(st[PAR + c, lane], st[M1 + c, lane], st[M2 + c, lane], st[GRAD + c, lane], h)
        st[PAR + c, lane] = p if has else st[PAR + c, lane]
        st[M1 + c, lane] = mi
        st[M2 + c, lane] = vi


@_jit
def step_view(ps, ms, vs, g_means, g_quats, g_scales, g_opac, g_sh0, g_shn, has, hyper, rows, deg0, chain, kr_o,
              kr_s, z, scaler):
    """The step of the map's rows ``rows`` [M] (distinct ids), in place.

    ``ps``, ``ms``, ``vs``: the map's raw parameters and Adam moments as flat float32 arrays, in the order means,
    quats, log scales, logits, sh0, shN (row r of parameter t at r * width); ``g_*``: the activated leaves'
    gradients [M, ...] (g_sh0 [M, 3]: the colours' at degree 0, else the DC coefficients'; g_shn [M, W]), or with
    ``chain`` False the raw parameters' (no chain rule); ``has[t]``: parameter t is stepped (its gradient given
    and its tensor not empty); ``hyper`` [6, 6] float64 (:data:`HYPER`); ``kr_o``, ``kr_s``: the
    regulariser's gradients per unit opacity and scale (opacity_reg / N, scale_reg / (3 N)); ``z`` [M, 3] normals
    and ``scaler`` > 0: the position noise of the updated row (0: none).

    Rows run :data:`LANES` at a time: copied into a scratch column each, stepped in one branch-free loop over the
    lanes (SIMD at the target's width), copied back; shN's variable-width rows are stepped in place, one by one."""
    pm, pq, ps_, po, p0, pn = ps
    f_o, f_s = np.float32(kr_o), np.float32(kr_s)
    c0, half, zero, one = np.float32(C0), np.float32(0.5), np.float32(0.0), np.float32(1.0)
    wn = pn.shape[0] // max(po.shape[0], 1)  # over the capacity: shN's row width
    h_m = _hyper(hyper, MEANS)
    h_q = _hyper(hyper, QUATS)
    h_s = _hyper(hyper, SCALES)
    h_o = _hyper(hyper, OPACITIES)
    h_0 = _hyper(hyper, SH0)
    h_n = _hyper(hyper, SHN)
    has_m, has_q, has_s, has_o, has_0, has_n = has[MEANS], has[QUATS], has[SCALES], has[OPACITIES], has[SH0], \
        has[SHN]
    noise = scaler > 0
    g_o2 = g_opac.reshape((g_opac.shape[0], 1))
    n = rows.shape[0]
    for bi in prange((n + LANES - 1) // LANES):
        full_width_vectors()
        st = np.empty((Z + 3, LANES), np.float32)
        base = bi * LANES
        count = min(LANES, n - base)
        for lane in range(LANES):  # the last group repeats its last row in the spare lanes
            i = base + min(lane, count - 1)
            g = rows[i]
            _gather_lane(st, lane, i, g, MEANS, pm, ms[0], vs[0], g_means, 3, has_m)
            _gather_lane(st, lane, i, g, QUATS, pq, ms[1], vs[1], g_quats, 4, has_q)
            _gather_lane(st, lane, i, g, SCALES, ps_, ms[2], vs[2], g_scales, 3, has_s)
            _gather_lane(st, lane, i, g, OPACITIES, po, ms[3], vs[3], g_o2, 1, has_o)
            _gather_lane(st, lane, i, g, SH0, p0, ms[4], vs[4], g_sh0, 3, has_0)
            for j in range(3):
                st[Z + j, lane] = z[i, j] if noise else zero
        for lane in range(LANES):
            for j in range(3):  # the chain rule and the regulariser, before the step
                c = COLS[SCALES] + j
                e = exp32(st[PAR + c, lane])
                gs = st[GRAD + c, lane] * e if chain else st[GRAD + c, lane]
                st[GRAD + c, lane] = gs + f_s * e
            c = COLS[OPACITIES]
            o = sigmoid32(st[PAR + c, lane])
            d = (one - o) * o
            go = st[GRAD + c, lane] * d if chain else st[GRAD + c, lane]
            st[GRAD + c, lane] = go + f_o * d
            for j in range(3):
                c = COLS[SH0] + j
                gc = st[GRAD + c, lane]
                if deg0 and chain:
                    gc = gc * c0 if st[PAR + c, lane] * c0 + half >= zero else zero
                st[GRAD + c, lane] = gc
            _step_lane(st, lane, MEANS, 3, has_m, h_m)
            _step_lane(st, lane, QUATS, 4, has_q, h_q)
            _step_lane(st, lane, SCALES, 3, has_s, h_s)
            _step_lane(st, lane, OPACITIES, 1, has_o, h_o)
            _step_lane(st, lane, SH0, 3, has_0, h_0)
            if noise:
                o = sigmoid32(st[PAR + COLS[OPACITIES], lane])
                e0 = exp32(st[PAR + COLS[SCALES], lane])
                e1 = exp32(st[PAR + COLS[SCALES] + 1, lane])
                e2 = exp32(st[PAR + COLS[SCALES] + 2, lane])
                q = COLS[QUATS]
                d0, d1, d2 = mean_delta(st[PAR + q, lane], st[PAR + q + 1, lane], st[PAR + q + 2, lane],
                                        st[PAR + q + 3, lane], e0 * e0, e1 * e1, e2 * e2, st[Z, lane],
                                        st[Z + 1, lane], st[Z + 2, lane], noise_gate(o, scaler))
                st[PAR, lane] = st[PAR, lane] + d0
                st[PAR + 1, lane] = st[PAR + 1, lane] + d1
                st[PAR + 2, lane] = st[PAR + 2, lane] + d2
        for lane in range(count):
            i = base + lane
            g = rows[i]
            if has_m:
                _scatter_lane(st, lane, g, MEANS, pm, ms[0], vs[0], 3)
            elif noise:
                for j in range(3):
                    pm[3 * g + j] = st[PAR + j, lane]
            if has_q:
                _scatter_lane(st, lane, g, QUATS, pq, ms[1], vs[1], 4)
            if has_s:
                _scatter_lane(st, lane, g, SCALES, ps_, ms[2], vs[2], 3)
            if has_o:
                _scatter_lane(st, lane, g, OPACITIES, po, ms[3], vs[3], 1)
            if has_0:
                _scatter_lane(st, lane, g, SH0, p0, ms[4], vs[4], 3)
            if has_n:
                for j in range(wn):
                    _adam(pn, ms[5], vs[5], wn * g + j, g_shn[i, j], h_n)
