"""Pinhole camera and SE(3) helpers, plus the adapters to Open3D's types.

Conventions (shared by the whole package):
- ``T_world_cam`` is camera-to-world, 4x4, metres, OpenCV axes (x right, y down, z forward).
- Pixel centres sit at integer coordinates, as in Open3D: ``u = fx * X / Z + cx``.
- Scaling an image by ``s`` scales ``fx, fy`` by ``s`` and maps ``cx -> (cx + 0.5) * s - 0.5``.
- Open3D's ``extrinsic`` is world-to-camera; it appears only in :func:`extrinsic_from_pose`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

if TYPE_CHECKING:  # torch loads on first use: the loop-verification process (pose.loop_worker) runs without it
    import torch


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of one image grid (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(f"camera focal lengths must be positive and finite, got fx={self.fx}, fy={self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError(f"camera principal point must be finite, got cx={self.cx}, cy={self.cy}")

    @classmethod
    def from_o3d(cls, intrinsic: o3d.camera.PinholeCameraIntrinsic) -> "Camera":
        fx, fy = intrinsic.get_focal_length()
        cx, cy = intrinsic.get_principal_point()
        return cls(int(intrinsic.width), int(intrinsic.height), float(fx), float(fy), float(cx), float(cy))

    def to_o3d(self) -> o3d.camera.PinholeCameraIntrinsic:
        return o3d.camera.PinholeCameraIntrinsic(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def scaled(self, scale: float) -> "Camera":
        """The camera of this image resampled by ``scale`` (sizes rounded to whole pixels)."""
        if scale == 1.0:
            return self
        return _scaled(self, scale)

    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def backproject(self, depth: torch.Tensor, stride: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-frame points of valid depth pixels.

        depth: [H, W] metres (0 = no measurement). Returns points [M, 3] and flat pixel indices [M].
        """
        import torch

        h, w = depth.shape
        vs = torch.arange(0, h, stride, device=depth.device)
        us = torch.arange(0, w, stride, device=depth.device)
        v, u = torch.meshgrid(vs, us, indexing="ij")
        z = depth[v, u]
        valid = z > 0
        u, v, z = u[valid], v[valid], z[valid]
        return self.unproject(u, v, z), (v.long() * w + u.long())

    def unproject(self, us, vs, z, T_world_cam=None):
        """Points [M, 3] at pixels (``us``, ``vs``) (centres at integers) and depths ``z`` [M] metres: in the camera
        frame, or in the world frame with ``T_world_cam``. The package's one back-projection: torch tensors give a
        float32 tensor, numpy arrays a float64 array."""
        if isinstance(z, np.ndarray):
            pts = np.stack([(us - self.cx) * z / self.fx, (vs - self.cy) * z / self.fy, z], axis=1).astype(np.float64)
            if T_world_cam is None:
                return pts
            T = np.asarray(T_world_cam, dtype=np.float64)
            return pts @ T[:3, :3].T + T[:3, 3]
        import torch

        pts = torch.stack([(us.float() - self.cx) * z / self.fx, (vs.float() - self.cy) * z / self.fy, z], -1)
        if T_world_cam is None:
            return pts
        T = torch.as_tensor(T_world_cam, dtype=torch.float32, device=pts.device)
        return pts @ T[:3, :3].T + T[:3, 3]


def check_pose(T: np.ndarray | torch.Tensor, what: str = "pose", tol: float = 1e-3) -> np.ndarray:
    """Return ``T`` as a float64 [4, 4] array; raise ValueError if it is not a finite rigid transform."""
    T = np.asarray(T.detach().cpu() if hasattr(T, "detach") else T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: contains NaN or Inf")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        raise ValueError(f"{what}: rotation block is not orthonormal with det +1 (non-rigid transform)")
    if np.abs(T[3] - np.array([0, 0, 0, 1.0])).max() > tol:
        raise ValueError(f"{what}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def extrinsic_from_pose(T_world_cam: np.ndarray) -> np.ndarray:
    """Open3D ``extrinsic`` (world-to-camera) from a camera-to-world pose."""
    return invert_pose(T_world_cam)


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (float64)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def pose_from_tum(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 camera-to-world pose from a TUM line's translation and (x, y, z, w) quaternion (any norm; float64,
    the inverse of :func:`pose_to_tum`). The Gaussians' (w, x, y, z) quaternions in torch turn into rotations
    with :func:`eligsir_o3d.render.projection.quat_to_rotmat`."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = t
    return T


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: z forward, y down) of a camera at ``eye`` looking at ``target``, its x
    axis level with the plane normal to ``up`` (default z-up). Looking along ``up``, another reference axis is
    taken."""
    z = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    z /= np.linalg.norm(z)
    up = np.asarray(up, np.float64)
    if abs(float(z @ up)) > 0.99:
        up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def pose_to_tum(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation [3], quaternion xyzw [4]) of a 4x4 pose."""
    return np.asarray(T[:3, 3], dtype=np.float64), rotmat_to_quat(T[:3, :3])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@lru_cache(maxsize=256)
def _scaled(camera: Camera, scale: float) -> Camera:
    """:meth:`Camera.scaled` (cameras are immutable: the few an update uses are made once)."""
    w = max(1, int(round(camera.width * scale)))
    h = max(1, int(round(camera.height * scale)))
    sx, sy = w / camera.width, h / camera.height
    return Camera(w, h, camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5, (camera.cy + 0.5) * sy - 0.5)
