"""Real spherical harmonics colour, degree 0..3, with the constants and sign conventions of 3DGS (and gsplat).

``sh`` holds per-Gaussian coefficients [N, K, 3] with K = (degree + 1)^2 (K may be larger: the extra bands are
ignored); ``dirs`` are the viewing directions (Gaussian centre minus camera centre, any length). As in 3DGS, the DC
band stores ``(rgb - 0.5) / C0`` and the evaluated colour is shifted by +0.5 and clamped at 0 from below.
"""

from __future__ import annotations

import math

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_of(k: int) -> int:
    """Highest complete degree that K coefficients hold (1 -> 0, 4 -> 1, 9 -> 2, 16 -> 3)."""
    d = int(math.isqrt(k)) - 1
    if d < 0:
        raise ValueError("need at least one SH coefficient")
    return min(d, 3)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient [..., 3] that renders ``rgb`` (before the +0.5 shift)."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * C0 + 0.5


def sh_bases(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """[N, (degree + 1)^2] real SH basis values at unit directions ``dirs`` [N, 3] (3DGS ordering and signs)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    cols = [torch.full_like(dirs[:, 0], C0)]
    if degree > 0:
        x, y, z = dirs.unbind(-1)
        cols += [-C1 * y, C1 * z, -C1 * x]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            cols += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
            if degree > 2:
                cols += [
                    C3[0] * y * (3.0 * xx - yy),
                    C3[1] * xy * z,
                    C3[2] * y * (4.0 * zz - xx - yy),
                    C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                    C3[4] * x * (4.0 * zz - xx - yy),
                    C3[5] * z * (xx - yy),
                    C3[6] * x * (xx - 3.0 * yy),
                ]
    return torch.stack(cols, -1)


def sh_eval(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Colours [N, 3] = max(0, sum_k basis_k(dir) sh[:, k] + 0.5).

    sh: [N, K, 3] coefficients; dirs: [N, 3] viewing directions (normalised here); degree: bands to use
    (default: all that K holds, at most 3).
    """
    if sh.dim() != 3 or sh.shape[-1] != 3:
        raise ValueError(f"sh must be [N, K, 3], got {tuple(sh.shape)}")
    if dirs.shape != (sh.shape[0], 3):
        raise ValueError(f"dirs must be [N, 3] = [{sh.shape[0]}, 3], got {tuple(dirs.shape)}")
    if degree is None:
        degree = sh_degree_of(sh.shape[1])
    k = num_sh_bases(degree)
    if k > sh.shape[1]:
        raise ValueError(f"SH degree {degree} needs {k} coefficients, sh has {sh.shape[1]}")
    if degree == 0:
        rgb = C0 * sh[:, 0]
    elif degree == 1 and sh.device.type == "cpu" and sh.dtype == torch.float32 and dirs.dtype == torch.float32:
        return _Sh1Cpu.apply(sh, dirs)  # one compiled pass each way (:mod:`._sh_kernels`)
    else:
        unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        rgb = (sh_bases(degree, unit.to(sh.dtype))[:, :, None] * sh[:, :k]).sum(1)
    return torch.clamp_min(rgb + 0.5, 0.0)


class _Sh1Cpu(torch.autograd.Function):
    """:func:`sh_eval` of degree 1 for float32 CPU tensors, forward and backward in compiled code."""

    @staticmethod
    def forward(ctx, sh, dirs):
        from ..runtime.jit import rows_threads
        from ._sh_kernels import sh1_forward

        sh_c, dirs_c = sh.detach().contiguous(), dirs.detach().contiguous()
        out = torch.empty(dirs_c.shape[0], 3, dtype=torch.float32)
        with rows_threads(dirs_c.shape[0], "sh1_forward"):
            sh1_forward(sh_c.numpy(), dirs_c.numpy(), out.numpy())
        ctx.save_for_backward(sh_c, dirs_c)
        return out

    @staticmethod
    def backward(ctx, grad):
        from ..runtime.jit import rows_threads
        from ._sh_kernels import sh1_backward

        sh_c, dirs_c = ctx.saved_tensors
        g_sh, g_dirs = torch.empty_like(sh_c), torch.empty_like(dirs_c)
        with rows_threads(dirs_c.shape[0], "sh1_backward"):
            sh1_backward(sh_c.numpy(), dirs_c.numpy(), grad.to(torch.float32).contiguous().numpy(), g_sh.numpy(),
                         g_dirs.numpy())
        return g_sh, g_dirs


def view_dirs(means: torch.Tensor, T_world_cam) -> torch.Tensor:
    """[N, 3] directions from the camera centre of ``T_world_cam`` (camera-to-world 4x4) to ``means`` [N, 3]."""
    T = torch.as_tensor(T_world_cam, dtype=means.dtype, device=means.device)
    return means - T[:3, 3]
