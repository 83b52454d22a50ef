"""The numba kernel of :class:`.adam.MapAdam`'s map-wide step on float32 CPU tensors: every parameter in one
compiled call, since torch's per-operator overhead on six small tensors was most of the step's cost.

Serial (no ``prange``): a pass over 20k rows takes tens of microseconds, less than a thread team's start-up.
Compiled lazily on first use and cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import numpy as np

from ..runtime.jit import jit_serial as _jit_serial


@_jit_serial
def adam_tensors(ps, gs, ms, vs, hyper):
    """One Adam step over every parameter t in ``ps`` (flat float32 arrays; ``gs``/``ms``/``vs`` the same shapes),
    in place: m += (1 - beta1)(g - m); v = v beta2 + (1 - beta2) g^2; p += a m / (sqrt(v) / b + eps), with
    hyper[t] = (1 - beta1, beta2, 1 - beta2, eps, a, b) in float32, a = -lr / (1 - beta1^k) and
    b = sqrt(1 - beta2^k) for the tensor's step count k. The complements are taken in float64 before the cast, as
    torch does (1 - float32(0.999) is 5e-5 off)."""
    for t in range(len(ps)):
        p, g, m, v = ps[t], gs[t], ms[t], vs[t]
        w, b2, w2, eps, a, b = hyper[t, 0], hyper[t, 1], hyper[t, 2], hyper[t, 3], hyper[t, 4], hyper[t, 5]
        for i in range(p.shape[0]):
            gi = g[i]
            mi = m[i] + w * (gi - m[i])
            vi = v[i] * b2 + w2 * gi * gi
            m[i] = mi
            v[i] = vi
            p[i] = p[i] + a * (mi / (np.sqrt(vi) / b + eps))
