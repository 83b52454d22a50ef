"""Numba kernels of a mapping update's work outside the renderer and the optimiser, for maps on the CPU:
3DGS-MCMC's position noise (the map's Adam step is :mod:`.adam`'s).

At the map sizes an online CPU budget affords (1k-30k Gaussians) the noise is a few arithmetic operations per
Gaussian, and torch's per-operator overhead (rotation matrices, covariances, a batched product) was most of its
cost. Here it is one pass over the rows.

- :func:`mcmc_noise` is :func:`.scheduling.mcmc.inject_noise`'s ``cov @ z * gate * scaler`` per row, with the
  random numbers still drawn by torch from the refiner's generator (the same stream as before);
  :func:`mcmc_noise_rows` does it for a culled update's rows where they lie in the map (raw parameters read and
  activated in the kernel, the means moved in place), without torch's gather of four parameters and scatter of
  the means.

The noise runs its rows in parallel from :data:`.core.jit.ROWS_LIMIT` rows on, on one thread below. Compiled
lazily on first use and cached on disk like the renderer's kernels.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from ..runtime.fmath import exp32, sigmoid32
from ..runtime.jit import jit as _jit
from ..runtime.jit import rows_threads


@numba.njit(inline="always", fastmath=False)
def mean_delta(w, x, y, zq, s0, s1, s2, z0, z1, z2, k):
    """(R diag(s0, s1, s2) R^T (z0, z1, z2)) * k, R the rotation of the quaternion (w, x, y, zq) (unnormalised)."""
    nq = max(np.float32(math.sqrt(w * w + x * x + y * y + zq * zq)), np.float32(1e-12))
    w, x, y, zq = w / nq, x / nq, y / nq, zq / nq
    r00, r01, r02 = 1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y)
    r10, r11, r12 = 2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x)
    r20, r21, r22 = 2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)
    # R^T z, scaled by s^2, then R
    a0 = (r00 * z0 + r10 * z1 + r20 * z2) * s0
    a1 = (r01 * z0 + r11 * z1 + r21 * z2) * s1
    a2 = (r02 * z0 + r12 * z1 + r22 * z2) * s2
    return (r00 * a0 + r01 * a1 + r02 * a2) * k, (r10 * a0 + r11 * a1 + r12 * a2) * k, \
        (r20 * a0 + r21 * a1 + r22 * a2) * k


@numba.njit(inline="always", fastmath=False)
def move_mean(means, g, quats, s0, s1, s2, z0, z1, z2, k):
    """means[g] += (R diag(s0, s1, s2) R^T (z0, z1, z2)) * k, R the rotation of quats[g] (unnormalised wxyz)."""
    d0, d1, d2 = mean_delta(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3], s0, s1, s2, z0, z1, z2, k)
    means[g, 0] += d0
    means[g, 1] += d1
    means[g, 2] += d2


@numba.njit(inline="always", fastmath=False)
def noise_gate(o, scaler):
    """sigmoid(100 ((1 - o) - 0.995)) * scaler: MCMC's gate to (nearly) transparent Gaussians."""
    return sigmoid32(np.float32(100.0) * ((np.float32(1.0) - o) - np.float32(0.995))) * scaler


@_jit
def _noise_rows(means, quats, scales, opacities, z, scaler):
    """means[g] += (R diag(s)^2 R^T z[g]) * sigmoid(100 ((1 - o) - 0.995)) * scaler; quats unnormalised wxyz,
    scales in metres, opacities in (0, 1)."""
    for g in prange(means.shape[0]):
        s0, s1, s2 = scales[g, 0] * scales[g, 0], scales[g, 1] * scales[g, 1], scales[g, 2] * scales[g, 2]
        move_mean(means, g, quats, s0, s1, s2, z[g, 0], z[g, 1], z[g, 2], noise_gate(opacities[g], scaler))


@_jit
def _noise_view(means, quats, log_scales, logit_opacities, rows, z, scaler):
    """:func:`_noise_rows` on the map's rows ``rows`` [M], read from its raw parameters (log scales, opacity
    logits) and moved in place: z[i] is row rows[i]'s normal triple. The activations are computed here in float32
    (:mod:`..runtime.fmath`), so a moved mean may differ from the gathered torch path's in the last bit."""
    for i in prange(rows.shape[0]):
        g = rows[i]
        o = sigmoid32(logit_opacities[g])
        e0 = exp32(log_scales[g, 0])
        e1 = exp32(log_scales[g, 1])
        e2 = exp32(log_scales[g, 2])
        move_mean(means, g, quats, e0 * e0, e1 * e1, e2 * e2, z[i, 0], z[i, 1], z[i, 2], noise_gate(o, scaler))


def mcmc_noise_rows(params: dict, rows, z, scaler: float) -> None:
    """In place on ``params["means"]`` (float32 CPU parameters of a map, raw as stored): the noise of
    :func:`mcmc_noise` on rows ``rows`` [M] (ids, distinct) with normals ``z`` [M, 3], without gathering the rows."""
    f = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with rows_threads(rows.shape[0], "noise_view"):
        _noise_view(params["means"].detach().numpy(), f(params["quats"]), f(params["scales"]),
                    f(params["opacities"]), f(rows), f(z), np.float32(scaler))


def mcmc_noise(means, quats, scales, opacities, z, scaler: float) -> None:
    """In place on ``means`` [N, 3] (a float32 CPU tensor): the covariance-shaped, opacity-gated noise of ``z``."""
    f = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with rows_threads(means.shape[0], "noise_rows"):
        _noise_rows(means.detach().numpy(), f(quats), f(scales), f(opacities), f(z), np.float32(scaler))
