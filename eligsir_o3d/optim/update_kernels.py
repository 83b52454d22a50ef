"""Numba kernels of a mapping update's work outside the renderer, for maps on the CPU: the Adam step over the
map's parameters and 3DGS-MCMC's position noise.

At the map sizes an online CPU budget affords (1k-30k Gaussians) these are a few arithmetic operations per
Gaussian, and torch's per-operator and per-optimizer overhead was most of their cost: the Adam steps of the six
parameter tensors took ~0.75 ms and the noise (rotation matrices, covariances, a batched product) ~1 ms of a
13 ms update at 1/4 scale on a 5k-Gaussian kitchen map (one thread). Here each is one pass over the rows.

- :func:`adam_step` is ``torch.optim.Adam``'s update (no weight decay, no AMSGrad) in float32, on the optimizer's
  own state tensors (``step``, ``exp_avg``, ``exp_avg_sq``), so a checkpoint, a relocation or a later torch step
  sees the state it expects; values agree with torch's to float32 rounding (torch's vector code may fuse a
  multiply-add where this does not).
- :func:`mcmc_noise` is :func:`.scheduling.mcmc.inject_noise`'s ``cov @ z * gate * scaler`` per row, with the
  random numbers still drawn by torch from the refiner's generator (the same stream as before);
  :func:`mcmc_noise_rows` does it for a culled update's rows where they lie in the map (raw parameters read and
  activated in the kernel, the means moved in place): torch's gather of four parameters and scatter of the means
  cost 0.55 ms of a kitchen update at 3k rows and 2.4 ms at 12k (two threads); this 0.3 / 0.7 ms.

The Adam kernels are serial (no ``prange``): a pass over 20k rows takes tens of microseconds, less than a thread
team's start-up. The noise runs its rows in parallel from :data:`.runtime.jit.ROWS_LIMIT` rows on (77k rows:
1.3 ms on one thread), on one thread below. Compiled lazily on first use and cached on disk like the renderer's
kernels.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import prange

from ..runtime.jit import jit as _jit
from ..runtime.jit import jit_serial as _jit_serial
from ..runtime.jit import rows_threads


def adam_state(opt, p) -> dict:
    """Torch Adam's state of parameter ``p`` in ``opt``, created as torch creates it on a first step (step 0, zero
    moments), so that a later torch step, checkpoints and relocation continue from it."""
    import torch

    state = opt.state[p]
    if not state:
        state["step"] = torch.tensor(0.0)
        state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    return state


def adam_step(opts) -> None:
    """One Adam step of each of ``opts`` (``torch.optim.Adam`` instances over float32 CPU parameters; those
    without a gradient are skipped), in place, in one compiled call."""
    ps, gs, ms, vs, hyper, a_rows, b_rows = [], [], [], [], [], [], []
    for opt in opts:
        group = opt.param_groups[0]
        b1, b2 = group["betas"]
        for p in group["params"]:
            if p.grad is None or p.numel() == 0:
                continue
            state = adam_state(opt, p)
            state["step"] += 1
            step = float(state["step"])
            bc1, bc2 = 1.0 - b1 ** step, 1.0 - b2 ** step
            ps.append(p.detach().view(-1).numpy())
            gs.append(p.grad.detach().contiguous().view(-1).numpy())
            ms.append(state["exp_avg"].view(-1).numpy())
            vs.append(state["exp_avg_sq"].view(-1).numpy())
            hyper.append((1.0 - b1, b2, 1.0 - b2, group["eps"]))
            a_rows.append(np.array([-group["lr"] / bc1], np.float32))  # one step size for the whole tensor
            b_rows.append(np.array([bc2 ** 0.5], np.float32))
    if ps:
        _adam_rows_scaled(tuple(ps), tuple(gs), tuple(ms), tuple(vs), np.array(hyper, np.float32), tuple(a_rows),
                          tuple(b_rows), np.array([len(p) for p in ps], np.int64))


def fits(opt) -> bool:
    """Whether :func:`adam_step` can run ``opt``: plain Adam settings over contiguous float32 CPU parameters."""
    import torch

    group = opt.param_groups[0]
    if len(opt.param_groups) != 1 or group.get("weight_decay", 0) or group.get("amsgrad") or group.get("maximize"):
        return False
    return all(p.device.type == "cpu" and p.dtype == torch.float32 and p.is_contiguous() for p in group["params"])


@numba.njit(inline="always", fastmath=False)
def _move(means, g, quats, s0, s1, s2, z0, z1, z2, k):
    """means[g] += (R diag(s0, s1, s2) R^T (z0, z1, z2)) * k, R the rotation of quats[g] (unnormalised wxyz)."""
    w, x, y, zq = quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
    nq = max(np.float32(math.sqrt(w * w + x * x + y * y + zq * zq)), np.float32(1e-12))
    w, x, y, zq = w / nq, x / nq, y / nq, zq / nq
    r00, r01, r02 = 1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y)
    r10, r11, r12 = 2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x)
    r20, r21, r22 = 2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)
    # R^T z, scaled by s^2, then R
    a0 = (r00 * z0 + r10 * z1 + r20 * z2) * s0
    a1 = (r01 * z0 + r11 * z1 + r21 * z2) * s1
    a2 = (r02 * z0 + r12 * z1 + r22 * z2) * s2
    means[g, 0] += (r00 * a0 + r01 * a1 + r02 * a2) * k
    means[g, 1] += (r10 * a0 + r11 * a1 + r12 * a2) * k
    means[g, 2] += (r20 * a0 + r21 * a1 + r22 * a2) * k


@numba.njit(inline="always", fastmath=False)
def _gate(o, scaler):
    """sigmoid(100 ((1 - o) - 0.995)) * scaler: MCMC's gate to (nearly) transparent Gaussians."""
    return np.float32(1.0) / (np.float32(1.0) + np.float32(math.exp(-np.float32(100.0) * (
        (np.float32(1.0) - o) - np.float32(0.995))))) * scaler


@_jit
def _noise_rows(means, quats, scales, opacities, z, scaler):
    """means[g] += (R diag(s)^2 R^T z[g]) * sigmoid(100 ((1 - o) - 0.995)) * scaler; quats unnormalised wxyz,
    scales in metres, opacities in (0, 1)."""
    for g in prange(means.shape[0]):
        s0, s1, s2 = scales[g, 0] * scales[g, 0], scales[g, 1] * scales[g, 1], scales[g, 2] * scales[g, 2]
        _move(means, g, quats, s0, s1, s2, z[g, 0], z[g, 1], z[g, 2], _gate(opacities[g], scaler))


@_jit
def _noise_view(means, quats, log_scales, logit_opacities, rows, z, scaler):
    """:func:`_noise_rows` on the map's rows ``rows`` [M], read from its raw parameters (log scales, opacity
    logits) and moved in place: z[i] is row rows[i]'s normal triple. The activations are computed here in float32
    (``math.exp``), so a moved mean may differ from the gathered torch path's in the last bit."""
    for i in prange(rows.shape[0]):
        g = rows[i]
        o = np.float32(1.0) / (np.float32(1.0) + np.float32(math.exp(-logit_opacities[g])))
        e0 = np.float32(math.exp(log_scales[g, 0]))
        e1 = np.float32(math.exp(log_scales[g, 1]))
        e2 = np.float32(math.exp(log_scales[g, 2]))
        _move(means, g, quats, e0 * e0, e1 * e1, e2 * e2, z[i, 0], z[i, 1], z[i, 2], _gate(o, scaler))


def mcmc_noise_rows(params: dict, rows, z, scaler: float) -> None:
    """In place on ``params["means"]`` (float32 CPU parameters of a map, raw as stored): the noise of
    :func:`mcmc_noise` on rows ``rows`` [M] (ids, distinct) with normals ``z`` [M, 3], without gathering the rows."""
    f = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with rows_threads(rows.shape[0]):
        _noise_view(params["means"].detach().numpy(), f(params["quats"]), f(params["scales"]),
                    f(params["opacities"]), f(rows), f(z), np.float32(scaler))


def mcmc_noise(means, quats, scales, opacities, z, scaler: float) -> None:
    """In place on ``means`` [N, 3] (a float32 CPU tensor): the covariance-shaped, opacity-gated noise of ``z``."""
    f = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    with rows_threads(means.shape[0]):
        _noise_rows(means.detach().numpy(), f(quats), f(scales), f(opacities), f(z), np.float32(scaler))


@_jit_serial
def _adam_rows_scaled(ps, gs, ms, vs, hyper, a_rows, b_rows, widths):
    """Adam over the rows of every parameter in ``ps`` (flat float32 arrays; ``gs``/``ms``/``vs`` the same shapes),
    with a step size and a bias correction per row (Gaussian): element i of parameter t belongs to row
    i // widths[t] (widths[t] = its length: one row, plain Adam); a_rows[t][r] = -lr_r / bias correction 1 of row
    r, b_rows[t][r] = sqrt(bias correction 2) of row r (an array of length 1: the same for every row);
    hyper[t] = (1 - beta1, beta2, 1 - beta2, eps), the complements taken in float64 as torch does
    (1 - float32(0.999) is 5e-5 off)."""
    for t in range(len(ps)):
        p, g, m, v, a, b, wd = ps[t], gs[t], ms[t], vs[t], a_rows[t], b_rows[t], widths[t]
        w, b2, w2, eps = hyper[t, 0], hyper[t, 1], hyper[t, 2], hyper[t, 3]
        for r in range(p.shape[0] // wd):
            ar, br = a[min(r, a.shape[0] - 1)], b[min(r, b.shape[0] - 1)]
            for i in range(r * wd, (r + 1) * wd):
                gi = g[i]
                mi = m[i] + w * (gi - m[i])
                vi = v[i] * b2 + w2 * gi * gi
                m[i] = mi
                v[i] = vi
                p[i] = p[i] + ar * (mi / (np.sqrt(vi) / br + eps))


def adam_rows_step(items) -> None:
    """One Adam step per item ``(param, grad, exp_avg, exp_avg_sq, a_rows, b_rows, (1 - beta1, beta2, 1 - beta2,
    eps))``, float32 CPU tensors with rows first, ``a_rows``/``b_rows`` [rows] or [1] as in
    :func:`_adam_rows_scaled`."""
    if not items:
        return
    _adam_rows_scaled(*adam_item_arrays(items))


def adam_item_arrays(items) -> tuple:
    """The flat numpy views the row-Adam kernels take, of items as :func:`adam_rows_step` describes: (params,
    grads, exp_avgs, exp_avg_sqs, hyper [n, 4], a_rows, b_rows, widths [n] row widths)."""
    f = lambda t: t.detach().contiguous().view(-1).numpy()  # noqa: E731
    ps = tuple(it[0].detach().view(-1).numpy() for it in items)
    ms = tuple(it[2].view(-1).numpy() for it in items)
    vs = tuple(it[3].view(-1).numpy() for it in items)
    widths = np.array([it[0].numel() // max(it[0].shape[0], 1) for it in items], np.int64)
    return (ps, tuple(f(it[1]) for it in items), ms, vs, np.array([it[6] for it in items], np.float32),
            tuple(f(it[4]) for it in items), tuple(f(it[5]) for it in items), widths)
