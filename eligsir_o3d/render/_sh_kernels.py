"""Numba kernels of degree-1 spherical-harmonic colour on the CPU (:func:`.sh.sh_eval`'s float32 CPU path).

Degree 1 is evaluated and differentiated per Gaussian in one pass each way: the torch formulation (normalise the
viewing direction, stack four basis values, a broadcast product and a sum, the clamp) is ~10 operators forward and
~15 in autograd's backward, ~1.5 ms of a 3.7k-Gaussian kitchen update on one thread (7.5 % of it); here ~0.1 ms.
Same formula and gradients as the torch path (to float32 rounding: the four bands are summed in order here).
Compiled lazily on first use and cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..runtime.jit import jit as _jit

C0 = np.float32(0.28209479177387814)
C1 = np.float32(0.4886025119029199)


@_jit
def sh1_forward(sh, dirs, out):
    """out[n, c] = max(0, C0 sh[n, 0, c] - C1 y sh[n, 1, c] + C1 z sh[n, 2, c] - C1 x sh[n, 3, c] + 0.5) with
    (x, y, z) = dirs[n] / max(|dirs[n]|, 1e-12); sh [N, K >= 4, 3], dirs [N, 3] float32."""
    for n in prange(dirs.shape[0]):
        dx, dy, dz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
        inv = np.float32(1.0) / max(np.float32(math.sqrt(dx * dx + dy * dy + dz * dz)), np.float32(1e-12))
        b1, b2, b3 = -C1 * (dy * inv), C1 * (dz * inv), -C1 * (dx * inv)
        for c in range(3):
            v = C0 * sh[n, 0, c] + b1 * sh[n, 1, c] + b2 * sh[n, 2, c] + b3 * sh[n, 3, c] + np.float32(0.5)
            out[n, c] = max(v, np.float32(0.0))


@_jit
def sh1_backward(sh, dirs, grad, g_sh, g_dirs):
    """Gradients of :func:`sh1_forward` for ``grad`` [N, 3] of its output: g_sh [N, K, 3] (bands above 1: zero)
    and g_dirs [N, 3] (through the normalisation; the clamp passes the gradient where its input is >= 0)."""
    for n in prange(dirs.shape[0]):
        dx, dy, dz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
        norm = np.float32(math.sqrt(dx * dx + dy * dy + dz * dz))
        inv = np.float32(1.0) / max(norm, np.float32(1e-12))
        ux, uy, uz = dx * inv, dy * inv, dz * inv
        b1, b2, b3 = -C1 * uy, C1 * uz, -C1 * ux
        d1 = np.float32(0.0)
        d2 = np.float32(0.0)
        d3 = np.float32(0.0)
        for c in range(3):
            v = C0 * sh[n, 0, c] + b1 * sh[n, 1, c] + b2 * sh[n, 2, c] + b3 * sh[n, 3, c] + np.float32(0.5)
            g = grad[n, c] if v >= np.float32(0.0) else np.float32(0.0)
            g_sh[n, 0, c] = C0 * g
            g_sh[n, 1, c] = b1 * g
            g_sh[n, 2, c] = b2 * g
            g_sh[n, 3, c] = b3 * g
            for k in range(4, sh.shape[1]):
                g_sh[n, k, c] = np.float32(0.0)
            d1 += g * sh[n, 1, c]
            d2 += g * sh[n, 2, c]
            d3 += g * sh[n, 3, c]
        gux, guy, guz = -C1 * d3, -C1 * d1, C1 * d2  # d loss / d unit direction
        if norm > np.float32(1e-12):  # d u / d v = (I - u u^T) / |v|; below the clamp u = v / 1e-12
            dot = ux * gux + uy * guy + uz * guz
            g_dirs[n, 0] = (gux - ux * dot) * inv
            g_dirs[n, 1] = (guy - uy * dot) * inv
            g_dirs[n, 2] = (guz - uz * dot) * inv
        else:
            g_dirs[n, 0] = gux * inv
            g_dirs[n, 1] = guy * inv
            g_dirs[n, 2] = guz * inv
