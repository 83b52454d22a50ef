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

from ..optim.update_kernels import move_mean, noise_gate
from ..runtime.fmath import exp32, sigmoid32
from ..runtime.jit import jit as _jit
from .device_reference import C0

HYPER = 6  # per stepped parameter: (a, b, 1 - beta1, beta2, 1 - beta2, eps), as base.adam_factors gives them
MEANS, QUATS, SCALES, OPACITIES, SH0, SHN = range(6)  # the rows of ``hyper`` and ``has`` in step_view


@_jit
def gather_activated(ps, rows, deg0, o_means, o_quats, o_scales, o_opac, o_colors):
    """Rows ``rows`` [M] of the raw map (``ps``: flat means, quats, log scales, logits, sh0, shN as in
    :func:`step_view`) into o_means [M, 3], o_quats [M, 4], o_scales [M, 3] (exp), o_opac [M] (sigmoid) and
    o_colors: [M, 3] RGB with ``deg0``, else [M, 3 + W] (sh0 then shN, the rows of a [M, K + 1, 3] tensor)."""
    pm, pq, ps_, po, p0, pn = ps
    c0, half, zero = np.float32(C0), np.float32(0.5), np.float32(0.0)
    wn = o_colors.shape[1] - 3
    for i in prange(rows.shape[0]):
        g = rows[i]
        for j in range(3):
            o_means[i, j] = pm[3 * g + j]
            o_scales[i, j] = exp32(ps_[3 * g + j])
        for j in range(4):
            o_quats[i, j] = pq[4 * g + j]
        o_opac[i] = sigmoid32(po[g])
        if deg0:
            for c in range(3):
                o_colors[i, c] = max(p0[3 * g + c] * c0 + half, zero)
        else:
            for c in range(3):
                o_colors[i, c] = p0[3 * g + c]
            for j in range(wn):
                o_colors[i, 3 + j] = pn[wn * g + j]


@numba.njit(inline="always", fastmath=False)
def _adam(p, m, v, t, k, grad, hyper):
    """torch's Adam on element k of parameter p (moments m, v), parameter number t of ``hyper``, in float32."""
    a, b = np.float32(hyper[t, 0]), np.float32(hyper[t, 1])
    w, b2, w2, eps = np.float32(hyper[t, 2]), np.float32(hyper[t, 3]), np.float32(hyper[t, 4]), \
        np.float32(hyper[t, 5])
    mi = m[k] + w * (grad - m[k])
    vi = v[k] * b2 + w2 * grad * grad
    m[k] = mi
    v[k] = vi
    p[k] = p[k] + a * (mi / (np.sqrt(vi) / b + eps))


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
    and ``scaler`` > 0: the position noise of the updated row (0: none)."""
    pm, pq, ps_, po, p0, pn = ps
    f_o, f_s = np.float32(kr_o), np.float32(kr_s)
    c0, half, zero = np.float32(C0), np.float32(0.5), np.float32(0.0)
    wn = pn.shape[0] // max(po.shape[0], 1)  # over the capacity: shN's row width
    means3, quats4 = pm.reshape((pm.shape[0] // 3, 3)), pq.reshape((pq.shape[0] // 4, 4))
    for i in prange(rows.shape[0]):
        g = rows[i]
        if has[MEANS]:
            for j in range(3):
                _adam(pm, ms[0], vs[0], MEANS, 3 * g + j, g_means[i, j], hyper)
        if has[QUATS]:
            for j in range(4):
                _adam(pq, ms[1], vs[1], QUATS, 4 * g + j, g_quats[i, j], hyper)
        if has[SCALES]:
            for j in range(3):
                e = exp32(ps_[3 * g + j])
                gs = g_scales[i, j] * e if chain else g_scales[i, j]
                _adam(ps_, ms[2], vs[2], SCALES, 3 * g + j, gs + f_s * e, hyper)
        if has[OPACITIES]:
            o = sigmoid32(po[g])
            d = (np.float32(1.0) - o) * o
            go = g_opac[i] * d if chain else g_opac[i]
            _adam(po, ms[3], vs[3], OPACITIES, g, go + f_o * d, hyper)
        if has[SH0]:
            for c in range(3):
                gc = g_sh0[i, c]
                if deg0 and chain:
                    gc = gc * c0 if p0[3 * g + c] * c0 + half >= zero else zero
                _adam(p0, ms[4], vs[4], SH0, 3 * g + c, gc, hyper)
        if has[SHN]:
            for j in range(wn):
                _adam(pn, ms[5], vs[5], SHN, wn * g + j, g_shn[i, j], hyper)
        if scaler > 0:
            o = sigmoid32(po[g])
            e0 = exp32(ps_[3 * g])
            e1 = exp32(ps_[3 * g + 1])
            e2 = exp32(ps_[3 * g + 2])
            move_mean(means3, g, quats4, e0 * e0, e1 * e1, e2 * e2, z[i, 0], z[i, 1],
                      z[i, 2], noise_gate(o, scaler))
