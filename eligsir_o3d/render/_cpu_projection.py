"""Numba twin of :func:`.projection.project` (EWA projection, culling, radii) with a hand-written backward pass.

Same math as the torch reference, term for term: normalised quaternion -> R, covariance (R S)(R S)^T, rotation into
the camera, the pinhole Jacobian with x/z and y/z clamped just outside the frustum, the 0.3 px^2 low-pass, the
conic, a 3-sigma radius of the larger eigenvalue and the same culling. It computes in float64 and stores float32,
so values agree with the float32 reference to rounding (a radius can differ by one pixel where 3 sqrt(lambda) lies
within ~1e-6 of an integer). The backward pass gives what autograd gives through the reference, including for
Gaussians behind the camera (whose upstream gradients are zero in a render) and at the Jacobian clamp.

Work: Gaussians run in lanes of :data:`LANES`. Each lane group is copied into a scratch array (one row per input
value), computed in one branch-free loop over the lanes that reads and writes only that scratch (so LLVM turns it
into SIMD code at the target's width, float64), and copied out. The 3x3 products are written out term by term in
the order of a plain triple loop (``acc = 0; acc += a[i, k] b[k, j]`` over k), the reference's order, so every
target and lane width gives the same bits. Tasks of :data:`BLOCK` Gaussians run in parallel (``prange``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

import numba

from ..runtime.jit import full_width_vectors
from ._cpu_kernels import _jit

BLOCK = 256  # Gaussians per parallel task (the scratch array is allocated once per task)
LANES = 16  # Gaussians computed side by side
# forward scratch rows: inputs (mean, quaternion, scale), outputs (means2d, conic, depth, radius)
F_M, F_Q, F_S, F_UV, F_CON, F_D, F_R, F_ROWS = 0, 3, 7, 10, 12, 15, 16, 17
# backward scratch rows: inputs (mean, quaternion, scale, v_means2d, v_conics, v_depths), outputs (v_means,
# v_quats, v_scales)
B_M, B_Q, B_S, B_GUV, B_GCON, B_GD, B_VM, B_VQ, B_VS, B_ROWS = 0, 3, 7, 10, 12, 15, 16, 19, 23, 26

_inline = numba.njit(inline="always", fastmath=False)


@_inline
def _limits(cam):
    fx, fy, cx, cy, width, height = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5]
    return ((cx + 0.5) / fx + 0.3 * (0.5 * width / fx), (width - cx - 0.5) / fx + 0.3 * (0.5 * width / fx),
            (cy + 0.5) / fy + 0.3 * (0.5 * height / fy), (height - cy - 0.5) / fy + 0.3 * (0.5 * height / fy))


@_inline
def _rows(V):
    """The world-to-camera matrix's top three rows as a tuple (v[4 i + k] = V[i, k]): values, not loads."""
    return (V[0, 0], V[0, 1], V[0, 2], V[0, 3], V[1, 0], V[1, 1], V[1, 2], V[1, 3], V[2, 0], V[2, 1], V[2, 2], V[2, 3])


@_inline
def _rotation(w, x, y, z):
    """Unit quaternion (w, x, y, z, |q|) and its rotation matrix, row by row."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    nq = max(norm, 1e-12)
    w, x, y, z = w / nq, x / nq, y / nq, z / nq
    return (w, x, y, z, nq,
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@_inline
def _mv3(a0, a1, a2, b0, b1, b2):
    """a . b summed from 0 in index order: one entry of a 3x3 product."""
    return ((0.0 + a0 * b0) + a1 * b1) + a2 * b2


@_inline
def _covariance(v, r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2):
    """T = Rv R diag(s) (row by row) and C = T T^T (its six distinct entries c00 c01 c02 c11 c12 c22; C is
    symmetric bit for bit: a product's factors commute exactly)."""
    m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
    m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
    m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
    t00, t01, t02 = (_mv3(v[0], v[1], v[2], m00, m10, m20), _mv3(v[0], v[1], v[2], m01, m11, m21),
                     _mv3(v[0], v[1], v[2], m02, m12, m22))
    t10, t11, t12 = (_mv3(v[4], v[5], v[6], m00, m10, m20), _mv3(v[4], v[5], v[6], m01, m11, m21),
                     _mv3(v[4], v[5], v[6], m02, m12, m22))
    t20, t21, t22 = (_mv3(v[8], v[9], v[10], m00, m10, m20), _mv3(v[8], v[9], v[10], m01, m11, m21),
                     _mv3(v[8], v[9], v[10], m02, m12, m22))
    return (t00, t01, t02, t10, t11, t12, t20, t21, t22,
            _mv3(t00, t01, t02, t00, t01, t02), _mv3(t00, t01, t02, t10, t11, t12),
            _mv3(t00, t01, t02, t20, t21, t22), _mv3(t10, t11, t12, t10, t11, t12),
            _mv3(t10, t11, t12, t20, t21, t22), _mv3(t20, t21, t22, t20, t21, t22))


@_inline
def _camera_point(v, m0, m1, m2, near):
    """The mean in the camera (px, py, pz), whether it lies in front, and the depth the Jacobian uses."""
    px = v[0] * m0 + v[1] * m1 + v[2] * m2 + v[3]
    py = v[4] * m0 + v[5] * m1 + v[6] * m2 + v[7]
    pz = v[8] * m0 + v[9] * m1 + v[10] * m2 + v[11]
    in_front = pz > near
    return px, py, pz, in_front, pz if in_front else 1.0


@_inline
def _cov2d(j00, j02, j11, j12, c00, c01, c02, c11, c12, c22, eps2d):
    """(a, b, c) of J C J^T + eps2d I for J = [[j00, 0, j02], [0, j11, j12]]."""
    a = j00 * j00 * c00 + 2.0 * j00 * j02 * c02 + j02 * j02 * c22 + eps2d
    b = j00 * j11 * c01 + j00 * j12 * c02 + j02 * j11 * c12 + j02 * j12 * c22
    c = j11 * j11 * c11 + 2.0 * j11 * j12 * c12 + j12 * j12 * c22 + eps2d
    return a, b, c


@_inline
def _load(st, row, src, g, lane, cols):
    for k in range(cols):
        st[row + k, lane] = src[g, k]


@_jit
def project_forward(means, quats, scales, V, cam, out_means2d, out_conics, out_depths, out_radii):
    """means [N, 3], quats [N, 4] wxyz, scales [N, 3] (float32); V [4, 4] world-to-camera (float64);
    cam (fx, fy, cx, cy, width, height, near, eps2d) float64. Writes means2d [N, 2], conics [N, 3], depths [N]
    (float32) and radii [N] (int32, 0 = culled)."""
    fx, fy, cx, cy, width, height, near, eps2d = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7]
    lxn, lxp, lyn, lyp = _limits(cam)
    v = _rows(V)
    n = means.shape[0]
    for bi in prange((n + BLOCK - 1) // BLOCK):
        full_width_vectors()
        st = np.empty((F_ROWS, LANES))
        stop = min(n, (bi + 1) * BLOCK)
        for base in range(bi * BLOCK, stop, LANES):
            for lane in range(LANES):  # the last group repeats its last Gaussian in the spare lanes
                g = min(base + lane, stop - 1)
                _load(st, F_M, means, g, lane, 3)
                _load(st, F_Q, quats, g, lane, 4)
                _load(st, F_S, scales, g, lane, 3)
            for lane in range(LANES):
                px, py, pz, in_front, zs = _camera_point(v, st[F_M, lane], st[F_M + 1, lane], st[F_M + 2, lane],
                                                         near)
                rot = _rotation(st[F_Q, lane], st[F_Q + 1, lane], st[F_Q + 2, lane], st[F_Q + 3, lane])
                cov = _covariance(v, rot[5], rot[6], rot[7], rot[8], rot[9], rot[10], rot[11], rot[12], rot[13],
                                  st[F_S, lane], st[F_S + 1, lane], st[F_S + 2, lane])
                tx = zs * min(max(px / zs, -lxn), lxp)
                ty = zs * min(max(py / zs, -lyn), lyp)
                j00, j02 = fx / zs, -fx * tx / (zs * zs)
                j11, j12 = fy / zs, -fy * ty / (zs * zs)
                a, b, c = _cov2d(j00, j02, j11, j12, cov[9], cov[10], cov[11], cov[12], cov[13], cov[14], eps2d)
                det = a * c - b * b
                ok = in_front & (det > 0.0)
                ds = det if ok else 1.0
                st[F_CON, lane] = c / ds
                st[F_CON + 1, lane] = -b / ds
                st[F_CON + 2, lane] = a / ds
                u = fx * px / zs + cx
                vv = fy * py / zs + cy
                st[F_UV, lane] = u
                st[F_UV + 1, lane] = vv
                st[F_D, lane] = pz if in_front else 0.0
                # the radius from float32 values, in the reference's order of operations
                a32, c32, ds32 = np.float32(a), np.float32(c), np.float32(ds)
                mid = np.float32(0.5) * (a32 + c32)
                lam = mid + np.float32(math.sqrt(max(mid * mid - ds32, np.float32(0.1))))
                r = np.float32(math.ceil(np.float32(3.0) * np.float32(math.sqrt(lam))))
                u32, v32 = np.float32(u), np.float32(vv)
                on_screen = (u32 + r > -0.5) & (u32 - r < width - 0.5) & (v32 + r > -0.5) & (v32 - r < height - 0.5)
                st[F_R, lane] = r if ok & on_screen else 0.0
            for lane in range(min(LANES, stop - base)):
                g = base + lane
                out_means2d[g, 0] = st[F_UV, lane]
                out_means2d[g, 1] = st[F_UV + 1, lane]
                for k in range(3):
                    out_conics[g, k] = st[F_CON + k, lane]
                out_depths[g] = st[F_D, lane]
                out_radii[g] = np.int32(st[F_R, lane])


@_jit
def project_backward(means, quats, scales, V, cam, v_means2d, v_conics, v_depths, out_v_means, out_v_quats,
                     out_v_scales):
    """Gradients of :func:`project_forward`'s means2d, conics and depths w.r.t. means, quats and scales. A Gaussian
    that no gradient reaches (culled, or outside the view: every incoming value 0) gets exact zeros."""
    fx, fy, near, eps2d = cam[0], cam[1], cam[6], cam[7]
    lxn, lxp, lyn, lyp = _limits(cam)
    v = _rows(V)
    n = means.shape[0]
    for bi in prange((n + BLOCK - 1) // BLOCK):
        full_width_vectors()
        st = np.empty((B_ROWS, LANES))
        stop = min(n, (bi + 1) * BLOCK)
        for base in range(bi * BLOCK, stop, LANES):
            reached = False
            for lane in range(LANES):
                g = min(base + lane, stop - 1)
                _load(st, B_M, means, g, lane, 3)
                _load(st, B_Q, quats, g, lane, 4)
                _load(st, B_S, scales, g, lane, 3)
                _load(st, B_GUV, v_means2d, g, lane, 2)
                _load(st, B_GCON, v_conics, g, lane, 3)
                st[B_GD, lane] = v_depths[g]
                reached |= (v_means2d[g, 0] != 0.0) | (v_means2d[g, 1] != 0.0) | (v_conics[g, 0] != 0.0) | \
                    (v_conics[g, 1] != 0.0) | (v_conics[g, 2] != 0.0) | (v_depths[g] != 0.0)
            if reached:
                for lane in range(LANES):
                    _backward_lane(st, lane, v, fx, fy, near, eps2d, lxn, lxp, lyn, lyp)
            for lane in range(min(LANES, stop - base)):
                g = base + lane
                zero = (v_means2d[g, 0] == 0.0) & (v_means2d[g, 1] == 0.0) & (v_conics[g, 0] == 0.0) & \
                    (v_conics[g, 1] == 0.0) & (v_conics[g, 2] == 0.0) & (v_depths[g] == 0.0)
                for k in range(3):
                    out_v_means[g, k] = 0.0 if zero else st[B_VM + k, lane]
                    out_v_scales[g, k] = 0.0 if zero else st[B_VS + k, lane]
                for k in range(4):
                    out_v_quats[g, k] = 0.0 if zero else st[B_VQ + k, lane]


@_inline
def _backward_lane(st, lane, v, fx, fy, near, eps2d, lxn, lxp, lyn, lyp):
    """The backward pass of one Gaussian, from its scratch column to its scratch column (branch-free)."""
    px, py, pz, in_front, zs = _camera_point(v, st[B_M, lane], st[B_M + 1, lane], st[B_M + 2, lane], near)
    w, x, y, z, nq, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(
        st[B_Q, lane], st[B_Q + 1, lane], st[B_Q + 2, lane], st[B_Q + 3, lane])
    s0, s1, s2 = st[B_S, lane], st[B_S + 1, lane], st[B_S + 2, lane]
    t00, t01, t02, t10, t11, t12, t20, t21, t22, c00, c01, c02, c11, c12, c22 = _covariance(
        v, r00, r01, r02, r10, r11, r12, r20, r21, r22, s0, s1, s2)
    ux, uy = px / zs, py / zs
    free_x = (-lxn <= ux) & (ux <= lxp)  # inside the clamp (bounds included, as torch.clamp) the gradient passes
    free_y = (-lyn <= uy) & (uy <= lyp)
    cl_x, cl_y = min(max(ux, -lxn), lxp), min(max(uy, -lyn), lyp)
    tx, ty = zs * cl_x, zs * cl_y
    j00, j02 = fx / zs, -fx * tx / (zs * zs)
    j11, j12 = fy / zs, -fy * ty / (zs * zs)
    j01, j10 = 0.0, 0.0
    a, b, c = _cov2d(j00, j02, j11, j12, c00, c01, c02, c11, c12, c22, eps2d)
    det = a * c - b * b
    # conic = (c, -b, a) / det  ->  a, b, c  (det = 1, a constant, where the Gaussian is culled)
    gA, gB, gC = st[B_GCON, lane], st[B_GCON + 1, lane], st[B_GCON + 2, lane]
    d2 = det * det
    live = in_front & (det > 0.0)
    ga = -gA * c * c / d2 + gB * b * c / d2 + gC * (1.0 / det - a * c / d2) if live else gC
    gb = gA * 2.0 * b * c / d2 + gB * (-1.0 / det - 2.0 * b * b / d2) + gC * 2.0 * a * b / d2 if live else -gB
    gc = gA * (1.0 / det - a * c / d2) + gB * a * b / d2 - gC * a * a / d2 if live else gA
    # cov2d = J C J^T; only cov2d[0, 1] is read off the diagonal, but a symmetric G gives the same leaf gradients
    # (the antisymmetric part cancels in C = T T^T). GJ = G J, vC = J^T G J, vJ = G J C (dL/dJ = 2 G J C)
    g00, g01, g10, g11 = ga, 0.5 * gb, 0.5 * gb, gc
    gj00, gj01, gj02 = (0.0 + g00 * j00) + g01 * j10, (0.0 + g00 * j01) + g01 * j11, (0.0 + g00 * j02) + g01 * j12
    gj10, gj11, gj12 = (0.0 + g10 * j00) + g11 * j10, (0.0 + g10 * j01) + g11 * j11, (0.0 + g10 * j02) + g11 * j12
    vc00, vc01, vc02 = (0.0 + j00 * gj00) + j10 * gj10, (0.0 + j00 * gj01) + j10 * gj11, (0.0 + j00 * gj02) + j10 * gj12
    vc10, vc11, vc12 = (0.0 + j01 * gj00) + j11 * gj10, (0.0 + j01 * gj01) + j11 * gj11, (0.0 + j01 * gj02) + j11 * gj12
    vc20, vc21, vc22 = (0.0 + j02 * gj00) + j12 * gj10, (0.0 + j02 * gj01) + j12 * gj11, (0.0 + j02 * gj02) + j12 * gj12
    vj00, vj01, vj02 = (_mv3(gj00, gj01, gj02, c00, c01, c02), _mv3(gj00, gj01, gj02, c01, c11, c12),
                        _mv3(gj00, gj01, gj02, c02, c12, c22))
    vj10, vj11, vj12 = (_mv3(gj10, gj11, gj12, c00, c01, c02), _mv3(gj10, gj11, gj12, c01, c11, c12),
                        _mv3(gj10, gj11, gj12, c02, c12, c22))
    g_tx = -2.0 * vj02 * fx / (zs * zs)
    g_ty = -2.0 * vj12 * fy / (zs * zs)
    g_zs = 2.0 * (-vj00 * fx / (zs * zs) + vj02 * 2.0 * fx * tx / (zs * zs * zs)
                  - vj11 * fy / (zs * zs) + vj12 * 2.0 * fy * ty / (zs * zs * zs))
    # t = zs * clamp(u / zs): d/du = 1, d/dzs = 0 inside the clamp; d/du = 0, d/dzs = the bound outside
    gx = 0.0 + g_tx if free_x else 0.0
    g_zs = g_zs if free_x else g_zs + g_tx * cl_x
    gy = 0.0 + g_ty if free_y else 0.0
    g_zs = g_zs if free_y else g_zs + g_ty * cl_y
    # means2d = (fx x / zs + cx, fy y / zs + cy)
    gu, gv = st[B_GUV, lane], st[B_GUV + 1, lane]
    gx += gu * fx / zs
    gy += gv * fy / zs
    g_zs += -gu * fx * px / (zs * zs) - gv * fy * py / (zs * zs)
    gz = 0.0 + (st[B_GD, lane] + g_zs) if in_front else 0.0  # zs = z and depth = z; behind the camera constants
    st[B_VM, lane] = v[0] * gx + v[4] * gy + v[8] * gz
    st[B_VM + 1, lane] = v[1] * gx + v[5] * gy + v[9] * gz
    st[B_VM + 2, lane] = v[2] * gx + v[6] * gy + v[10] * gz
    # C = T T^T, T = Rv M, M = R diag(s): vT = vC T, dL/dM = 2 Rv^T vT
    vt00, vt01, vt02 = (_mv3(vc00, vc01, vc02, t00, t10, t20), _mv3(vc00, vc01, vc02, t01, t11, t21),
                        _mv3(vc00, vc01, vc02, t02, t12, t22))
    vt10, vt11, vt12 = (_mv3(vc10, vc11, vc12, t00, t10, t20), _mv3(vc10, vc11, vc12, t01, t11, t21),
                        _mv3(vc10, vc11, vc12, t02, t12, t22))
    vt20, vt21, vt22 = (_mv3(vc20, vc21, vc22, t00, t10, t20), _mv3(vc20, vc21, vc22, t01, t11, t21),
                        _mv3(vc20, vc21, vc22, t02, t12, t22))
    vm00, vm01, vm02 = (2.0 * _mv3(v[0], v[4], v[8], vt00, vt10, vt20),
                        2.0 * _mv3(v[0], v[4], v[8], vt01, vt11, vt21),
                        2.0 * _mv3(v[0], v[4], v[8], vt02, vt12, vt22))
    vm10, vm11, vm12 = (2.0 * _mv3(v[1], v[5], v[9], vt00, vt10, vt20),
                        2.0 * _mv3(v[1], v[5], v[9], vt01, vt11, vt21),
                        2.0 * _mv3(v[1], v[5], v[9], vt02, vt12, vt22))
    vm20, vm21, vm22 = (2.0 * _mv3(v[2], v[6], v[10], vt00, vt10, vt20),
                        2.0 * _mv3(v[2], v[6], v[10], vt01, vt11, vt21),
                        2.0 * _mv3(v[2], v[6], v[10], vt02, vt12, vt22))
    st[B_VS, lane] = _mv3(vm00, vm10, vm20, r00, r10, r20)
    st[B_VS + 1, lane] = _mv3(vm01, vm11, vm21, r01, r11, r21)
    st[B_VS + 2, lane] = _mv3(vm02, vm12, vm22, r02, r12, r22)
    # dL/dR = dL/dM diag(s)
    vr00, vr01, vr02 = vm00 * s0, vm01 * s1, vm02 * s2
    vr10, vr11, vr12 = vm10 * s0, vm11 * s1, vm12 * s2
    vr20, vr21, vr22 = vm20 * s0, vm21 * s1, vm22 * s2
    vw = 2.0 * (-z * vr01 + y * vr02 + z * vr10 - x * vr12 - y * vr20 + x * vr21)
    vx = 2.0 * (y * vr01 + z * vr02 + y * vr10 - 2.0 * x * vr11 - w * vr12 + z * vr20 + w * vr21 - 2.0 * x * vr22)
    vy = 2.0 * (-2.0 * y * vr00 + x * vr01 + w * vr02 + x * vr10 + z * vr12 - w * vr20 + z * vr21 - 2.0 * y * vr22)
    vz = 2.0 * (-2.0 * z * vr00 - w * vr01 + x * vr02 + w * vr10 - 2.0 * z * vr11 + y * vr12 + x * vr20 + y * vr21)
    # q_unit = q / max(|q|, 1e-12)
    dot = w * vw + x * vx + y * vy + z * vz
    big = nq > 1e-12
    st[B_VQ, lane] = (vw - w * dot if big else vw) / nq
    st[B_VQ + 1, lane] = (vx - x * dot if big else vx) / nq
    st[B_VQ + 2, lane] = (vy - y * dot if big else vy) / nq
    st[B_VQ + 3, lane] = (vz - z * dot if big else vz) / nq
