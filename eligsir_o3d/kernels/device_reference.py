"""The view's rows and their step in plain torch, on any device and without a host sync: the reference of the
fused stages (:mod:`.triton_select`, :mod:`.triton_step`) and their fallback where Triton is absent.

- :func:`select_rows`: the conservative in-view test of :func:`.render.culling.in_view` (float64), the hits
  compacted in ascending order into a fixed capacity, and their raw parameters gathered and activated. The count
  stays a device tensor; rows past it are padding that renders nothing.
- :func:`step_rows`: the chain rule from the activated leaves to the raw parameters, the MCMC regulariser's
  gradient, torch's Adam (float32, bias corrections given as host scalars) and the covariance-shaped, opacity-gated
  position noise, written in place on the map's rows ``idx[:count]``. Rows outside them keep their bits.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

C0 = 0.28209479177387814  # Y_0^0
PAD_SCALE = 1e-3  # metres: the scale of a padding row (opacity 0: it draws nothing)
STEPPED = ("means", "scales", "quats", "opacities", "sh0", "shN")


class Selection(NamedTuple):
    """The rows in view, in a capacity C: ids [C] int64 (ascending in [0, count), then 0), count [1] int64 (may
    exceed C: then the first C hits), and the activated leaves of those rows (padding: means 0, quats (1, 0, 0, 0),
    scales 1e-3 m, opacities 0, colours 0): means [C, 3] m, quats [C, 4] raw wxyz, scales [C, 3] m, opacities [C],
    colors [C, 3] RGB (degree 0) or [C, K + 1, 3] SH coefficients."""

    idx: torch.Tensor
    count: torch.Tensor
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


class AdamScalars(NamedTuple):
    """One parameter's Adam step as host scalars: betas, eps, ``a = -lr / (1 - beta1^k)`` and ``b = sqrt(1 -
    beta2^k)`` with k the parameter's step count after this step."""

    beta1: float
    beta2: float
    eps: float
    a: float
    b: float


def adam_scalars(lr: float, beta1: float, beta2: float, eps: float, step: int) -> AdamScalars:
    """The host scalars of step number ``step`` (1 for the first) of torch's Adam."""
    return AdamScalars(beta1, beta2, eps, -lr * (1.0 / (1.0 - beta1 ** step)), math.sqrt(1.0 - beta2 ** step))


def view_hits(means, log_scales, V, cam) -> torch.Tensor:
    """[N] bool: the rows (raw means [N, 3], log scales [N, 3]) that :func:`.render.culling.in_view` keeps for the
    world-to-camera rows ``V`` (12 host floats) and ``cam`` (:func:`.render.culling.camera_bounds`), in float64."""
    fx, fy, cx, cy, w, h, near, jb2, lp = (float(c) for c in cam)
    m = means.detach().double()
    mx, my, mz = m.unbind(-1)
    x = mx * V[0] + my * V[1] + mz * V[2] + V[3]
    y = mx * V[4] + my * V[5] + mz * V[6] + V[7]
    z = mx * V[8] + my * V[9] + mz * V[10] + V[11]
    front = z > near
    zs = torch.where(front, z, torch.ones_like(z))
    s = torch.exp(log_scales.detach().double().amax(-1).clamp(max=80.0))
    r = 3.0 * torch.sqrt(s * s * jb2 / (zs * zs) + lp) * 1.001 + 2.0
    u, v = fx * x / zs + cx, fy * y / zs + cy
    return front & (u + r > -0.5) & (u - r < w - 0.5) & (v + r > -0.5) & (v - r < h - 0.5)


def select_rows(means, log_scales, quats, logit_opac, sh0, shN, V, cam, capacity: int,
                sh_degree: int) -> Selection:
    """:class:`Selection` of the map's raw rows (means [N, 3], log scales [N, 3], quats [N, 4], logits [N],
    sh0 [N, 1, 3], shN [N, K, 3]) in view of ``V``/``cam`` (see :func:`view_hits`), in ``capacity`` rows."""
    dev, n, C = means.device, means.shape[0], int(capacity)
    hits = view_hits(means, log_scales, V, cam)
    pos = torch.cumsum(hits, 0) - 1  # [N] int64: each hit's place among the hits
    count = pos[-1:] + 1 if n else torch.zeros(1, dtype=torch.int64, device=dev)
    slot = torch.where(hits & (pos < C), pos, C)  # misses and overflow: the dump slot C
    idx = torch.zeros(C + 1, dtype=torch.int64, device=dev)
    idx.scatter_(0, slot, torch.arange(n, device=dev))
    idx = idx[:C]
    live = torch.arange(C, device=dev) < count  # [C] bool
    if n == 0:  # nothing to gather from: every row is padding
        src = [torch.zeros((C,) + t.shape[1:], dtype=t.dtype, device=dev) for t in (means, quats, log_scales,
                                                                                       logit_opac, sh0, shN)]
    else:
        src = [t.detach()[idx] for t in (means, quats, log_scales, logit_opac, sh0, shN)]
    m, q, ls, lo, s0, sn = src
    col = live[:, None]
    means_c = torch.where(col, m, 0.0)
    quats_c = torch.where(col, q, 0.0)
    quats_c[:, 0] = torch.where(live, q[:, 0], 1.0)
    scales_c = torch.where(col, torch.exp(ls), PAD_SCALE)
    opac_c = torch.where(live, torch.sigmoid(lo), 0.0)
    if sh_degree == 0:
        colors = torch.where(col, torch.clamp_min(s0[:, 0] * C0 + 0.5, 0.0), 0.0)
    else:
        colors = torch.where(live[:, None, None], torch.cat([s0, sn], 1), 0.0)
    return Selection(idx, count, means_c, quats_c, scales_c, opac_c, colors)


def raw_grads(rows: dict, grads: dict, opacity_reg: float, scale_reg: float, n_map: int) -> dict:
    """The gradients of the raw parameters of the view's rows (``rows``: their raw values [C, ...]) from those of
    the activated leaves (``grads``: means, quats, scales, opacities, colors; None or absent = not stepped) and the
    regulariser ``(opacity_reg * sum sigmoid(logit) + scale_reg * sum exp(log_scale) / 3) / n_map``."""
    out = {}
    if grads.get("means") is not None:
        out["means"] = grads["means"]
    if grads.get("quats") is not None:
        out["quats"] = grads["quats"]
    if grads.get("scales") is not None:
        e = torch.exp(rows["scales"])
        out["scales"] = grads["scales"] * e + (scale_reg / (3.0 * n_map)) * e
    if grads.get("opacities") is not None:
        o = torch.sigmoid(rows["opacities"])
        d = (1.0 - o) * o
        out["opacities"] = grads["opacities"] * d + (opacity_reg / n_map) * d
    gc = grads.get("colors")
    if gc is not None and gc.ndim == 2:  # degree 0: through clamp_min(sh0 C0 + 0.5, 0) (its gradient where >= 0)
        rgb = rows["sh0"][:, 0] * C0 + 0.5
        out["sh0"] = torch.where(rgb >= 0, gc * C0, 0.0)[:, None]
    elif gc is not None:
        out["sh0"], out["shN"] = gc[:, :1], gc[:, 1:]
    return out


def adam_rows(p, m, v, g, s: AdamScalars):
    """torch's Adam step of rows ``p`` (moments ``m``, ``v``, gradient ``g``) in float32: the new (p, m, v)."""
    w, b2, w2 = float(1.0 - s.beta1), float(s.beta2), float(1.0 - s.beta2)
    m = m + w * (g - m)
    v = v * b2 + w2 * g * g
    return p + s.a * (m / (torch.sqrt(v) / s.b + s.eps)), m, v


def noise_rows(means, quats, log_scales, logits, z, scaler: float):
    """means [C, 3] + (R diag(s^2) R^T z) sigmoid(100 ((1 - o) - 0.995)) scaler, R the rotation of the
    normalised quats [C, 4] (norm clamped at 1e-12), s = exp(log scales), o = sigmoid(logits), z [C, 3]."""
    q = quats / torch.clamp_min(torch.linalg.vector_norm(quats, dim=-1, keepdim=True), 1e-12)
    w, x, y, zq = q.unbind(-1)
    R = torch.stack([1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y),
                     2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x),
                     2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)], -1).view(-1, 3, 3)
    s2 = torch.exp(log_scales) ** 2
    a = (R.transpose(1, 2) @ z[..., None])[..., 0] * s2
    gate = torch.sigmoid(100.0 * ((1.0 - torch.sigmoid(logits)) - 0.995)) * scaler
    return means + (R @ a[..., None])[..., 0] * gate[:, None]


def step_rows(params: dict, exp_avg: dict, exp_avg_sq: dict, idx, count, grads: dict, adam: dict,
              opacity_reg: float = 0.0, scale_reg: float = 0.0, n_map: int = 1, scaler: float = 0.0,
              z=None) -> None:
    """In place on the map's raw ``params`` [N, ...] and their moments (dicts by parameter name): the step of the
    rows ``idx[:min(count, C)]`` (idx [C] int64, count [1] int64) from the activated leaves' gradients ``grads``
    [C, ...] (see :func:`raw_grads`), with ``adam[name]`` (:class:`AdamScalars`) for each stepped parameter; then,
    where ``scaler`` > 0, the position noise of normals ``z`` [C, 3] on the updated rows (:func:`noise_rows`)."""
    n, C = params["means"].shape[0], idx.shape[0]
    if n == 0 or C == 0:
        return
    live = torch.arange(C, device=idx.device) < count  # [C] bool
    old = {k: params[k].detach()[idx] for k in STEPPED}
    g = raw_grads(old, grads, opacity_reg, scale_reg, n_map)
    new, moments = dict(old), {}
    for k, gk in g.items():
        if old[k].numel() == 0:
            continue
        new[k], mk, vk = adam_rows(old[k], exp_avg[k][idx], exp_avg_sq[k][idx], gk, adam[k])
        moments[k] = (mk, vk)
    if scaler > 0 and z is not None:
        new["means"] = noise_rows(new["means"], new["quats"], new["scales"], new["opacities"], z, scaler)
    # padding rows (id 0) write what row 0 gets anyway: its new values where it is the first hit, else its own
    first_is_0 = (idx[0] == 0) & live[0]
    writes = [(params[k], new[k], old[k]) for k in new if k == "means" or k in g]
    writes += [(exp_avg[k], mk, exp_avg[k][idx]) for k, (mk, _) in moments.items()]
    writes += [(exp_avg_sq[k], vk, exp_avg_sq[k][idx]) for k, (_, vk) in moments.items()]
    for dst, val, prev in writes:
        if val.numel() == 0 or (val is prev):
            continue
        shape = (C,) + (1,) * (val.ndim - 1)
        pad = torch.where(first_is_0, val[:1], prev)
        dst.detach().index_copy_(0, idx, torch.where(live.view(shape), val, pad))
