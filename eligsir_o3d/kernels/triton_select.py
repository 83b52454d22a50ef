""":func:`.device_reference.select_rows` in Triton: three launches. The view test (float64, the bound of
:func:`.render.culling.in_view`'s torch branch) writes a mask and each block's hit count; torch's cumsum turns the
counts into block offsets; the gather compacts each block's hits in order (a block scan) into the capacity and
writes their activated leaves, the padding rows past the count, and the count. The view's float64 host scalars
travel as their int64 bit patterns (a Triton float argument is float32)."""

from __future__ import annotations

import struct

import torch
import triton.language as tl

from .device_reference import C0, PAD_SCALE, Selection
from .triton_launch import cdiv, device_function, kernel, launch, pow2
_C0 = tl.constexpr(C0)
_PAD_SCALE = tl.constexpr(PAD_SCALE)


@device_function
def _f64(bits):
    """The float64 whose bit pattern is ``bits`` (a host int)."""
    return bits.to(tl.int64).to(tl.float64, bitcast=True)


@kernel
def _hits_kernel(means, ls, mask_ptr, counts_ptr, N, V, cam, BLOCK: tl.constexpr):
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = r < N
    mx = tl.load(means + r * 3, mask=ok, other=0.0).to(tl.float64)
    my = tl.load(means + r * 3 + 1, mask=ok, other=0.0).to(tl.float64)
    mz = tl.load(means + r * 3 + 2, mask=ok, other=0.0).to(tl.float64)
    x = mx * _f64(V[0]) + my * _f64(V[1]) + mz * _f64(V[2]) + _f64(V[3])
    y = mx * _f64(V[4]) + my * _f64(V[5]) + mz * _f64(V[6]) + _f64(V[7])
    z = mx * _f64(V[8]) + my * _f64(V[9]) + mz * _f64(V[10]) + _f64(V[11])
    lmax = tl.maximum(tl.load(ls + r * 3, mask=ok, other=0.0), tl.load(ls + r * 3 + 1, mask=ok, other=0.0))
    lmax = tl.maximum(lmax, tl.load(ls + r * 3 + 2, mask=ok, other=0.0)).to(tl.float64)
    front = z > _f64(cam[6])
    zs = tl.where(front, z, 1.0)
    s = tl.exp(tl.minimum(lmax, 80.0))
    rad = 3.0 * tl.sqrt(s * s * _f64(cam[7]) / (zs * zs) + _f64(cam[8])) * 1.001 + 2.0
    u = _f64(cam[0]) * x / zs + _f64(cam[2])
    v = _f64(cam[1]) * y / zs + _f64(cam[3])
    hit = ok & front & (u + rad > -0.5) & (u - rad < _f64(cam[4]) - 0.5)
    hit = hit & (v + rad > -0.5) & (v - rad < _f64(cam[5]) - 0.5)
    tl.store(mask_ptr + r, hit.to(tl.int8), mask=ok)
    tl.store(counts_ptr + tl.program_id(0), tl.sum(hit.to(tl.int64), 0))


@kernel
def _gather_kernel(mask_ptr, offs_ptr, NB, means, ls, quats, lo, sh0, shN, idx, count, o_m, o_q, o_s, o_o, o_c,
                   N, C, K3, DEG0: tl.constexpr, BLOCK: tl.constexpr, WSH: tl.constexpr):
    p = tl.program_id(0)
    r = p * BLOCK + tl.arange(0, BLOCK)
    total = tl.load(offs_ptr + NB - 1)
    hit = tl.load(mask_ptr + r, mask=r < N, other=0).to(tl.int64)
    before = tl.load(offs_ptr + p - 1, mask=(p > 0) & (p < NB + 1), other=0)
    pos = before + tl.cumsum(hit, 0) - hit
    put = (hit != 0) & (pos < C)
    tl.store(idx + pos, r.to(tl.int64), mask=put)
    c4 = tl.arange(0, 4)[None, :]
    r2, q2, put2 = r[:, None], pos[:, None], put[:, None]
    tl.store(o_m + q2 * 3 + c4, tl.load(means + r2 * 3 + c4, mask=put2 & (c4 < 3)), mask=put2 & (c4 < 3))
    tl.store(o_q + q2 * 4 + c4, tl.load(quats + r2 * 4 + c4, mask=put2), mask=put2)
    tl.store(o_s + q2 * 3 + c4, tl.exp(tl.load(ls + r2 * 3 + c4, mask=put2 & (c4 < 3))), mask=put2 & (c4 < 3))
    tl.store(o_o + pos, tl.sigmoid(tl.load(lo + r, mask=put)), mask=put)
    if DEG0:
        rgb = tl.maximum(tl.load(sh0 + r2 * 3 + c4, mask=put2 & (c4 < 3)) * _C0 + 0.5, 0.0)
        tl.store(o_c + q2 * 3 + c4, rgb, mask=put2 & (c4 < 3))
    else:
        cs = tl.arange(0, WSH)[None, :]
        a0, an = put2 & (cs < 3), put2 & (cs >= 3) & (cs < K3 + 3)
        sh = tl.load(sh0 + r2 * 3 + cs, mask=a0, other=0.0) + tl.load(shN + r2 * K3 + cs - 3, mask=an, other=0.0)
        tl.store(o_c + q2 * (K3 + 3) + cs, sh, mask=a0 | an)
    # padding: the capacity's positions past the count
    q = p * BLOCK + tl.arange(0, BLOCK)
    pad = (q < C) & (q >= total)
    q2, pad2 = q[:, None], pad[:, None]
    tl.store(idx + q, tl.zeros([BLOCK], tl.int64), mask=pad)
    tl.store(o_m + q2 * 3 + c4, tl.zeros([BLOCK, 4], tl.float32), mask=pad2 & (c4 < 3))
    tl.store(o_q + q2 * 4 + c4, tl.where(c4 == 0, 1.0, 0.0) + tl.zeros([BLOCK, 4], tl.float32), mask=pad2)
    tl.store(o_s + q2 * 3 + c4, tl.zeros([BLOCK, 4], tl.float32) + _PAD_SCALE, mask=pad2 & (c4 < 3))
    tl.store(o_o + q, tl.zeros([BLOCK], tl.float32), mask=pad)
    cw = tl.arange(0, WSH)[None, :]
    tl.store(o_c + q2 * (K3 + 3) + cw, tl.zeros([BLOCK, WSH], tl.float32), mask=pad2 & (cw < K3 + 3))
    tl.store(count + tl.arange(0, 1), total + tl.zeros([1], tl.int64), mask=(tl.arange(0, 1) + p) == 0)


def _bits(values) -> tuple[int, ...]:
    """The float64 ``values``' bit patterns as int64s."""
    return struct.unpack(f"<{len(values)}q", struct.pack(f"<{len(values)}d", *values))


def select_rows(means, log_scales, quats, logit_opac, sh0, shN, V, cam, capacity: int,
                sh_degree: int) -> Selection:
    """:func:`.device_reference.select_rows` (same arguments and outputs) in three launches."""
    dev, n, C = means.device, means.shape[0], int(capacity)
    block = 1024 if dev.type == "cpu" else 256
    nb = max(1, cdiv(n, block))
    mask = torch.empty(max(n, 1), dtype=torch.int8, device=dev)
    counts = torch.empty(nb, dtype=torch.int64, device=dev)
    f = [t.detach().contiguous() for t in (means, log_scales, quats, logit_opac, sh0, shN)]
    launch(_hits_kernel, (nb,), f[0], f[1], mask, counts, n, _bits(V), _bits(cam), BLOCK=block)
    offsets = torch.cumsum(counts, 0)
    k3 = shN.shape[1] * 3
    f32 = dict(dtype=torch.float32, device=dev)
    idx, count = torch.empty(C, dtype=torch.int64, device=dev), torch.empty(1, dtype=torch.int64, device=dev)
    out = [torch.empty(C, 3, **f32), torch.empty(C, 4, **f32), torch.empty(C, 3, **f32), torch.empty(C, **f32),
           torch.empty((C, 3) if sh_degree == 0 else (C, k3 // 3 + 1, 3), **f32)]
    grid = max(nb, cdiv(C, block))
    launch(_gather_kernel, (grid,), mask, offsets, nb, *f[:1], f[1], f[2], f[3], f[4], f[5], idx, count, *out,
           n, C, k3, DEG0=sh_degree == 0, BLOCK=block, WSH=pow2(k3 + 3))
    return Selection(idx, count, *out)
