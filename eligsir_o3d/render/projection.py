"""EWA projection of 3D Gaussians and tile binning, in differentiable PyTorch.

This is the first half of every tile renderer (the second half, compositing, is backend specific). The math
follows 3DGS / gsplat's "classic" mode: Jacobian of the pinhole projection with clamped x/z and y/z, a 0.3 px^2
low-pass added to the 2D covariance (more where a map is drawn finer than it was supervised), a 3-sigma screen
radius, 16x16 tiles, front-to-back order by view depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D

TILE = 16
NEAR = 0.01


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities; ``radii == 0`` marks culled Gaussians."""

    means2d: torch.Tensor  # [N, 2] pixels (integer pixel centres)
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c) for [[a, b], [b, c]]
    depths: torch.Tensor  # [N] view-space z, metres
    radii: torch.Tensor  # [N] int32, pixels; 0 = not visible


@dataclass
class TileBins:
    """Depth-sorted Gaussian ids per tile, padded: ``ids[t, k] == -1`` past the tile's list."""

    ids: torch.Tensor  # [T, K] int64
    tiles_x: int
    tiles_y: int


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] quaternions (w, x, y, z), any norm -> [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def world_to_cam(T_world_cam, device, dtype=torch.float32) -> torch.Tensor:
    """[4, 4] world-to-camera matrix (gsplat's ``viewmat``) from a camera-to-world pose."""
    T = torch.as_tensor(T_world_cam, dtype=torch.float64)
    R, t = T[:3, :3], T[:3, 3]
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R.T
    V[:3, 3] = -R.T @ t
    return V.to(device=device, dtype=dtype)


def world_to_cam_np(T_world_cam, rounded: bool = False) -> np.ndarray:
    """:func:`world_to_cam` in float64 numpy (host arithmetic, no tensor operator): the same numbers; ``rounded``:
    rounded to float32 (as ``world_to_cam(T, dtype=float32)``). The last poses' matrices are kept: the result is
    shared, not to be written."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    return _world_to_cam_np(T.tobytes(), T.shape, rounded)


@lru_cache(maxsize=8)
def _world_to_cam_np(T_bytes: bytes, shape: tuple, rounded: bool) -> np.ndarray:
    T = np.frombuffer(T_bytes, np.float64).reshape(shape)
    V = np.eye(4)
    V[:3, :3] = R = T[:3, :3].T
    V[:3, 3] = -R @ T[:3, 3]
    return V.astype(np.float32).astype(np.float64) if rounded else V


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera,
            T_world_cam, low_pass: float = EPS2D) -> Projection:
    """Project Gaussians (means [N, 3] world, quats [N, 4] wxyz, scales [N, 3] metres) into ``camera``;
    ``low_pass``: the variance [px^2] added to every 2D covariance (see :meth:`.GaussianMap.low_pass`)."""
    V = world_to_cam(T_world_cam, means.device, means.dtype)
    R_v, t_v = V[:3, :3], V[:3, 3]
    p = means @ R_v.T + t_v  # [N, 3]
    x, y, z = p.unbind(-1)
    in_front = z > NEAR
    zs = torch.where(in_front, z, torch.ones_like(z))

    R = quat_to_rotmat(quats)
    M = R * scales[:, None, :]  # R S
    cov_w = M @ M.transpose(1, 2)  # [N, 3, 3]
    cov_c = R_v @ cov_w @ R_v.T

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    # 3DGS/gsplat clamp the Jacobian's x/z, y/z just outside the frustum so off-screen Gaussians stay sane
    # (gsplat's principal point is ours + 0.5: its pixel centres sit at half-integers).
    tan_x, tan_y = 0.5 * camera.width / fx, 0.5 * camera.height / fy
    lim_x_pos = (camera.width - cx - 0.5) / fx + 0.3 * tan_x
    lim_x_neg = (cx + 0.5) / fx + 0.3 * tan_x
    lim_y_pos = (camera.height - cy - 0.5) / fy + 0.3 * tan_y
    lim_y_neg = (cy + 0.5) / fy + 0.3 * tan_y
    tx = zs * torch.clamp(x / zs, -lim_x_neg, lim_x_pos)
    ty = zs * torch.clamp(y / zs, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)], -1).reshape(-1, 2, 3)
    cov2d = J @ cov_c @ J.transpose(1, 2)
    a = cov2d[:, 0, 0] + low_pass
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + low_pass
    det = a * c - b * b
    ok = in_front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)

    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det_s).clamp_min(0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam))
        m = means2d
        # Culled: behind the camera, degenerate, or the 3-sigma box misses the image.
        on_screen = (m[:, 0] + radii > -0.5) & (m[:, 0] - radii < camera.width - 0.5) & \
                    (m[:, 1] + radii > -0.5) & (m[:, 1] - radii < camera.height - 0.5)
        radii = torch.where(ok & on_screen, radii, torch.zeros_like(radii)).to(torch.int32)
    return Projection(means2d, conics, torch.where(in_front, z, zero), radii)


def bin_tiles(proj: Projection, width: int, height: int) -> TileBins:
    """Assign each visible Gaussian to every 16x16 tile its 3-sigma box touches; sort each tile front to back."""
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    n_tiles = tiles_x * tiles_y
    device = proj.means2d.device
    with torch.no_grad():
        vis = torch.nonzero(proj.radii > 0).squeeze(1)
        if vis.numel() == 0:
            return TileBins(torch.full((n_tiles, 0), -1, dtype=torch.long, device=device), tiles_x, tiles_y)
        m = proj.means2d[vis].detach()
        r = proj.radii[vis].float()
        # Pixel centres are at integer coordinates; pixel u covers [u - 0.5, u + 0.5).
        x0 = ((m[:, 0] - r + 0.5) / TILE).floor().clamp(0, tiles_x).long()
        x1 = ((m[:, 0] + r + 0.5) / TILE).floor().add(1).clamp(0, tiles_x).long()
        y0 = ((m[:, 1] - r + 0.5) / TILE).floor().clamp(0, tiles_y).long()
        y1 = ((m[:, 1] + r + 0.5) / TILE).floor().add(1).clamp(0, tiles_y).long()
        w_t, h_t = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
        counts = w_t * h_t
        total = int(counts.sum())
        if total == 0:
            return TileBins(torch.full((n_tiles, 0), -1, dtype=torch.long, device=device), tiles_x, tiles_y)
        g = torch.repeat_interleave(torch.arange(vis.numel(), device=device), counts)
        start = torch.cumsum(counts, 0) - counts
        local = torch.arange(total, device=device) - start[g]
        tx = x0[g] + local % w_t[g]
        ty = y0[g] + local // w_t[g]
        tile = ty * tiles_x + tx
        # Front to back inside each tile: sort by depth rank, then (stably) by tile.
        depth_rank = torch.empty_like(vis)
        depth_rank[torch.argsort(proj.depths[vis].detach(), stable=True)] = torch.arange(vis.numel(), device=device)
        key = tile * vis.numel() + depth_rank[g]
        order = torch.argsort(key)
        tile, g = tile[order], vis[g[order]]
        per_tile = torch.bincount(tile, minlength=n_tiles)
        k_max = int(per_tile.max())
        tstart = torch.cumsum(per_tile, 0) - per_tile
        slot = torch.arange(total, device=device) - tstart[tile]
        ids = torch.full((n_tiles, k_max), -1, dtype=torch.long, device=device)
        ids[tile, slot] = g
    return TileBins(ids, tiles_x, tiles_y)
