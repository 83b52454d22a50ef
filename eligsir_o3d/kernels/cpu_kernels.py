"""Numba kernels of the ``numba`` kernel set's step: Adam over the rows one view touched, in place.

Compiled lazily on first use and cached on disk like the renderer's kernels (:mod:`..runtime.jit`).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from ..runtime.jit import jit as _jit


@_jit
def adam_rows(ps, gs, ms, vs, hyper, widths, rows):
    """Adam over the rows ``rows`` [M] of every parameter t: ``ps[t]``, ``ms[t]``, ``vs[t]`` flat float32 arrays of
    the map (row r at r * widths[t]), ``gs[t]`` the gradient of the gathered rows (row i at i * widths[t]);
    hyper[t] = (a, b, 1 - beta1, beta2, 1 - beta2, eps) in float64, a = -lr / bias correction 1, b = sqrt(bias
    correction 2). m = m + (1 - beta1)(g - m); v = v beta2 + (1 - beta2) g^2; p = p + a m / (sqrt(v) / b + eps), in
    float32 (torch's Adam)."""
    for t in range(len(ps)):
        p, g, m, v, wd = ps[t], gs[t], ms[t], vs[t], widths[t]
        ar, br = np.float32(hyper[t, 0]), np.float32(hyper[t, 1])
        w, b2, w2, eps = np.float32(hyper[t, 2]), np.float32(hyper[t, 3]), np.float32(hyper[t, 4]), \
            np.float32(hyper[t, 5])
        for r in prange(rows.shape[0]):
            base = rows[r] * wd
            for j in range(wd):
                i = base + j
                gi = g[r * wd + j]
                mi = m[i] + w * (gi - m[i])
                vi = v[i] * b2 + w2 * gi * gi
                m[i] = mi
                v[i] = vi
                p[i] = p[i] + ar * (mi / (np.sqrt(vi) / br + eps))
