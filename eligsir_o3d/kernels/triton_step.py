""":func:`.device_reference.step_rows` as one Triton kernel: per view row, the chain rule from the activated leaves,
the regulariser's gradient, torch's Adam (float32) of every stepped parameter and the position noise on the
updated row, written in place on the map's row ``idx[i]`` for i < min(count, C). Rows past the count and rows
outside the view are neither read nor written."""

from __future__ import annotations

import triton.language as tl

from .device_reference import C0, STEPPED, AdamScalars
from .triton_launch import cdiv, device_function, kernel, launch, pow2
_C0 = tl.constexpr(C0)


@device_function
def _adam(p_ptr, m_ptr, v_ptr, offs, mask, g, h):
    """torch's Adam of the elements ``offs``: stores m and v, returns the new parameter values; h = (1 - beta1,
    beta2, 1 - beta2, eps, a, b)."""
    m = tl.load(m_ptr + offs, mask=mask, other=0.0)
    v = tl.load(v_ptr + offs, mask=mask, other=0.0)
    p = tl.load(p_ptr + offs, mask=mask, other=0.0)
    m = m + h[0] * (g - m)
    v = v * h[1] + h[2] * g * g
    tl.store(m_ptr + offs, m, mask=mask)
    tl.store(v_ptr + offs, v, mask=mask)
    return p + h[4] * (m / (tl.sqrt(v) / h[5] + h[3]))


@device_function
def _col(t, cols, j):
    """Column j of a [BLOCK, W] tile."""
    return tl.sum(tl.where(cols == j, t, 0.0), 1)


@kernel
def _step_kernel(idx_ptr, count_ptr, C, pm, mm, vm, gm, pq, mq, vq, gq, ps, ms, vs, gs, po, mo, vo, go,
                 p0, m0, v0, pn, mn, vn, gc, z_ptr, hm, hq, hs, ho, h0, hn, kr_o, kr_s, scaler, K3,
                 HAS_M: tl.constexpr, HAS_Q: tl.constexpr, HAS_S: tl.constexpr, HAS_O: tl.constexpr,
                 HAS_C: tl.constexpr, DEG0: tl.constexpr, NOISE: tl.constexpr, BLOCK: tl.constexpr,
                 WSH: tl.constexpr):
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < tl.minimum(tl.load(count_ptr), C)
    g = tl.load(idx_ptr + i, mask=live, other=0)
    cols = tl.arange(0, 4)[None, :]
    r2, l2 = g[:, None], live[:, None]
    m3, m4 = l2 & (cols < 3), l2 & (cols < 4)
    q = tl.load(pq + r2 * 4 + cols, mask=m4, other=0.0)
    if HAS_Q:
        q = _adam(pq, mq, vq, r2 * 4 + cols, m4, tl.load(gq + i[:, None] * 4 + cols, mask=m4, other=0.0), hq)
        tl.store(pq + r2 * 4 + cols, q, mask=m4)
    ls = tl.load(ps + r2 * 3 + cols, mask=m3, other=0.0)
    if HAS_S:
        e = tl.exp(ls)
        gsr = tl.load(gs + i[:, None] * 3 + cols, mask=m3, other=0.0) * e + kr_s * e
        ls = _adam(ps, ms, vs, r2 * 3 + cols, m3, gsr, hs)
        tl.store(ps + r2 * 3 + cols, ls, mask=m3)
    lo = tl.load(po + g, mask=live, other=0.0)
    if HAS_O:
        o = tl.sigmoid(lo)
        d = (1.0 - o) * o
        lo = _adam(po, mo, vo, g, live, tl.load(go + i, mask=live, other=0.0) * d + kr_o * d, ho)
        tl.store(po + g, lo, mask=live)
    if HAS_C:
        if DEG0:
            s0 = tl.load(p0 + r2 * 3 + cols, mask=m3, other=0.0)
            gcol = tl.load(gc + i[:, None] * 3 + cols, mask=m3, other=0.0)
            g0 = tl.where(s0 * _C0 + 0.5 >= 0.0, gcol * _C0, 0.0)
            tl.store(p0 + r2 * 3 + cols, _adam(p0, m0, v0, r2 * 3 + cols, m3, g0, h0), mask=m3)
        else:
            cs = tl.arange(0, WSH)[None, :]
            gsh = tl.load(gc + i[:, None] * (K3 + 3) + cs, mask=l2 & (cs < K3 + 3), other=0.0)
            a0 = l2 & (cs < 3)
            tl.store(p0 + r2 * 3 + cs, _adam(p0, m0, v0, r2 * 3 + cs, a0, gsh, h0), mask=a0)
            an = l2 & (cs >= 3) & (cs < K3 + 3)
            on = r2 * K3 + cs - 3
            tl.store(pn + on, _adam(pn, mn, vn, on, an, gsh, hn), mask=an)
    x = tl.load(pm + r2 * 3 + cols, mask=m3, other=0.0)
    if HAS_M:
        x = _adam(pm, mm, vm, r2 * 3 + cols, m3, tl.load(gm + i[:, None] * 3 + cols, mask=m3, other=0.0), hm)
    if NOISE:
        qw, qx, qy, qz = _col(q, cols, 0), _col(q, cols, 1), _col(q, cols, 2), _col(q, cols, 3)
        nq = tl.maximum(tl.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / nq, qx / nq, qy / nq, qz / nq
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        zt = tl.load(z_ptr + i[:, None] * 3 + cols, mask=m3, other=0.0)
        z0, z1, z2 = _col(zt, cols, 0), _col(zt, cols, 1), _col(zt, cols, 2)
        s2 = tl.exp(ls)
        s2 = s2 * s2
        a0 = (r00 * z0 + r10 * z1 + r20 * z2) * _col(s2, cols, 0)
        a1 = (r01 * z0 + r11 * z1 + r21 * z2) * _col(s2, cols, 1)
        a2 = (r02 * z0 + r12 * z1 + r22 * z2) * _col(s2, cols, 2)
        k = tl.sigmoid(100.0 * ((1.0 - tl.sigmoid(lo)) - 0.995)) * scaler
        d0 = (r00 * a0 + r01 * a1 + r02 * a2) * k
        d1 = (r10 * a0 + r11 * a1 + r12 * a2) * k
        d2 = (r20 * a0 + r21 * a1 + r22 * a2) * k
        x = x + tl.where(cols == 0, d0[:, None], tl.where(cols == 1, d1[:, None], d2[:, None]))
    if HAS_M or NOISE:
        tl.store(pm + r2 * 3 + cols, x, mask=m3)


def _h(s: AdamScalars | None) -> tuple:
    if s is None:
        return (0.0,) * 6
    return (float(1.0 - s.beta1), float(s.beta2), float(1.0 - s.beta2), float(s.eps), float(s.a), float(s.b))


def step_rows(params: dict, exp_avg: dict, exp_avg_sq: dict, idx, count, grads: dict, adam: dict,
              opacity_reg: float = 0.0, scale_reg: float = 0.0, n_map: int = 1, scaler: float = 0.0,
              z=None) -> None:
    """:func:`.device_reference.step_rows` (same arguments and meaning) in one launch."""
    n, C = params["means"].shape[0], idx.shape[0]
    if n == 0 or C == 0:
        return
    gc = grads.get("colors")
    k3 = params["shN"].shape[1] * 3
    has = {k: grads.get(k) is not None for k in ("means", "quats", "scales", "opacities")}
    noise = scaler > 0 and z is not None
    p = {k: params[k].detach() for k in STEPPED}
    dummy = p["means"]

    def pmv(k):
        return (p[k], exp_avg[k], exp_avg_sq[k]) if p[k].numel() else (dummy, dummy, dummy)

    def grad(k):
        return grads[k].contiguous() if grads.get(k) is not None else dummy

    block = 1024 if idx.device.type == "cpu" else 128
    launch(_step_kernel, (cdiv(C, block),), idx, count, C,
           *pmv("means"), grad("means"), *pmv("quats"), grad("quats"), *pmv("scales"), grad("scales"),
           *pmv("opacities"), grad("opacities"), *pmv("sh0"), *pmv("shN"),
           dummy if gc is None else gc.contiguous(), z.contiguous() if noise else dummy,
           *(_h(adam.get(k)) for k in ("means", "quats", "scales", "opacities", "sh0", "shN")),
           float(opacity_reg / n_map), float(scale_reg / (3.0 * n_map)),
           float(scaler), k3, HAS_M=has["means"], HAS_Q=has["quats"], HAS_S=has["scales"], HAS_O=has["opacities"],
           HAS_C=gc is not None, DEG0=gc is not None and gc.ndim == 2, NOISE=noise, BLOCK=block,
           WSH=pow2(k3 + 3))
