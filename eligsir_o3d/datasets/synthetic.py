"""The embedded synthetic sequence: a textured room ray-cast with Open3D, with exact poses and depth.

A 5 x 4 x 2.6 m room (tiled wooden floor, four differently papered walls with a window, a painting and a
skirting board, a panelled ceiling) holding a cabinet, a ball on it, a striped column, a chequered crate and a
bookshelf. The camera makes one loop around the room per sequence (any ``n_frames``), looking inward with some
height and yaw variation, so every wall and object is seen from several sides and the last frame comes back
near the first. World axes: z up, metres; the room spans x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.6].

Depth is the exact z-depth of the ray-cast mesh through each pixel centre (pixel centres at integer coordinates,
as in :class:`Camera` and Open3D's unprojection). Colour is a procedural texture of the hit position on the hit
object, times Lambert shading from a ceiling light; it depends only on the surface point, so every view agrees
on it (what a static Gaussian map can represent exactly). Frames are rendered on first access and cached.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import open3d as o3d

from ..core.camera import Camera, look_at
from . import textures as tx
from .base import DatasetError, RGBDSequence

ROOM_MIN = np.array([-2.5, -2.0, 0.0])
ROOM_MAX = np.array([2.5, 2.0, 2.6])
LIGHT = np.array([0.2, -0.3, 2.35])


@dataclass
class Solid:
    """One ray-casting geometry: world triangles, its local frame, how its normals are computed, its texture."""

    name: str
    vertices: np.ndarray  # [V, 3] world
    triangles: np.ndarray  # [T, 3]
    center: np.ndarray  # [3] origin of the local frame
    R: np.ndarray  # [3, 3] local -> world rotation
    kind: str  # "flat" (face normals), "sphere" or "cylinder" (smooth analytic normals)
    texture: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (local points [M, 3], local normals) -> rgb [M, 3]


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _solid(name, mesh: o3d.t.geometry.TriangleMesh, center, kind, texture, yaw_deg=0.0, offset=None) -> Solid:
    v = mesh.vertex.positions.numpy().astype(np.float64)
    if offset is not None:  # centre the primitive on its local origin
        v = v + offset
    R = _rot_z(yaw_deg)
    center = np.asarray(center, dtype=np.float64)
    return Solid(name, v @ R.T + center, mesh.triangle.indices.numpy(), center, R, kind, texture)


def _box(name, size, center, texture, yaw_deg=0.0) -> Solid:
    size = np.asarray(size, dtype=np.float64)
    return _solid(name, o3d.t.geometry.TriangleMesh.create_box(*size), center, "flat", texture, yaw_deg, -size / 2)


def build_room(seed: int = 0) -> list[Solid]:
    """The room's solids; ``seed`` moves the objects by a few centimetres and reseeds the texture noise."""
    rng = np.random.default_rng(seed)
    noise = tx.ValueNoise(rng)
    jitter = lambda: np.r_[rng.uniform(-0.08, 0.08, 2), 0.0]  # noqa: E731
    size = ROOM_MAX - ROOM_MIN
    room = _box("room", size, (ROOM_MIN + ROOM_MAX) / 2, tx.room(noise, ROOM_MIN, ROOM_MAX))
    return [
        room,
        _box("cabinet", (1.0, 0.6, 0.75), np.r_[0.1, 0.0, 0.375] + jitter(), tx.wood(noise), 10.0),
        _solid("ball", o3d.t.geometry.TriangleMesh.create_sphere(0.2, 24), np.r_[0.3, 0.05, 0.95] + jitter(),
               "sphere", tx.beach_ball()),
        _solid("column", o3d.t.geometry.TriangleMesh.create_cylinder(0.17, 1.0, 32, 1),
               np.r_[-0.5, 0.55, 0.5] + jitter(), "cylinder", tx.bands()),
        _box("crate", (0.45, 0.45, 0.45), np.r_[-0.55, -0.6, 0.225] + jitter(), tx.crate(noise), 25.0),
        _box("bookshelf", (0.35, 1.2, 1.8), (2.3, -0.7, 0.9), tx.bookshelf(rng)),
    ]


def camera_path(n_frames: int) -> list[np.ndarray]:
    """Camera-to-world poses of one loop around the room (OpenCV axes), looking inward."""
    poses = []
    for s in np.arange(n_frames) / n_frames:
        a = 2 * np.pi * s
        eye = np.array([1.7 * np.cos(a), 1.3 * np.sin(a), 1.35 + 0.2 * np.sin(2 * a)])
        side = np.array([-np.sin(a), np.cos(a), 0.0])  # tangent: the gaze swings left and right of the centre
        target = np.array([0.0, 0.0, 0.75 + 0.15 * np.sin(3 * a)]) + 0.9 * np.sin(3 * a + 0.5) * side
        poses.append(look_at(eye, target))
    return poses


class SyntheticRoom(RGBDSequence):
    """The synthetic room sequence. Depth is Float32 metres (``depth_scale`` 1.0) or, with
    ``depth_dtype="uint16"``, millimetres (``depth_scale`` 1000) like a sensor PNG."""

    def __init__(self, n_frames: int = 120, width: int = 160, height: int = 120, seed: int = 0, fps: float = 30.0,
                 depth_dtype: str = "float32", shading: bool = True) -> None:
        if n_frames < 1 or width < 8 or height < 8 or not fps > 0:
            raise DatasetError(f"synthetic scene needs n_frames >= 1, width and height >= 8 and fps > 0; got "
                               f"n_frames={n_frames}, {width}x{height}, fps={fps}")
        if depth_dtype not in ("float32", "uint16"):
            raise DatasetError(f"depth_dtype must be 'float32' or 'uint16', got {depth_dtype!r}")
        f = 0.8 * width  # ~64 degrees horizontal field of view at any resolution
        camera = Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
        super().__init__(name="synthetic_room", path=None, camera=camera,
                         depth_scale=1.0 if depth_dtype == "float32" else 1000.0,
                         timestamps=np.arange(n_frames) / fps, poses=camera_path(n_frames), format="synthetic")
        self.seed, self.depth_dtype, self.shading = seed, depth_dtype, shading
        self.solids = build_room(seed)
        self.scene = o3d.t.geometry.RaycastingScene()
        for s in self.solids:
            self.scene.add_triangles(o3d.core.Tensor(s.vertices.astype(np.float32)),
                                     o3d.core.Tensor(s.triangles.astype(np.uint32)))
        self._cache: dict[int, tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]] = {}
        self._dirs_cam: tuple[Camera | None, np.ndarray | None] = (None, None)  # pixel rays of the last camera

    def render(self, T_world_cam: np.ndarray, camera: Camera | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Colour [H, W, 3] float32 in [0, 1] and z-depth [H, W] float32 metres (0 = no hit) from any pose."""
        cam = camera or self.camera
        T = np.asarray(T_world_cam, dtype=np.float64)
        if self._dirs_cam[0] != cam:
            v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
            self._dirs_cam = (cam, np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1))
        dirs = self._dirs_cam[1] @ T[:3, :3].T  # [H, W, 3], camera-frame z = 1
        rays = np.concatenate([np.broadcast_to(T[:3, 3], dirs.shape), dirs], -1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        depth = hit["t_hit"].numpy()  # the ray's z component is 1 in the camera frame: t is z-depth
        ids = hit["geometry_ids"].numpy().astype(np.int64)
        ok = np.isfinite(depth)
        depth = np.where(ok, depth, 0.0).astype(np.float32)
        color = np.zeros((cam.height, cam.width, 3), dtype=np.float32)
        points = T[:3, 3] + dirs[ok] * depth[ok, None].astype(np.float64)
        normals = hit["primitive_normals"].numpy()[ok].astype(np.float64)
        color[ok] = self._shade(points, normals, dirs[ok], ids[ok])
        return color, depth

    def _shade(self, points, normals, dirs, ids) -> np.ndarray:  # [M, 3] each -> rgb [M, 3]
        rgb = np.zeros_like(points)
        for gid, s in enumerate(self.solids):
            m = ids == gid
            if not m.any():
                continue
            local = (points[m] - s.center) @ s.R
            n = normals[m] @ s.R
            if s.kind == "sphere":
                n = local
            elif s.kind == "cylinder":
                side = np.abs(n[:, 2]) < 0.5
                n[side] = local[side] * [1.0, 1.0, 0.0]
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            n *= -np.sign(np.sum((n @ s.R.T) * dirs[m], axis=1, keepdims=True) + 1e-12)  # face the camera
            albedo = s.texture(local, n)
            if self.shading:
                to_light = LIGHT - points[m]
                to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
                albedo = albedo * (0.45 + 0.6 * np.clip(np.sum((n @ s.R.T) * to_light, axis=1), 0, 1))[:, None]
            rgb[m] = albedo
        return np.clip(rgb, 0.0, 1.0)

    def _read_images(self, i: int) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]:
        if i not in self._cache:
            color, depth = self.render(self.poses[i])
            color8 = np.round(color * 255).astype(np.uint8)
            depth = np.round(depth * 1000).astype(np.uint16) if self.depth_dtype == "uint16" else depth
            self._cache[i] = (o3d.t.geometry.Image(o3d.core.Tensor(color8)),
                              o3d.t.geometry.Image(o3d.core.Tensor(depth[..., None])))
        color, depth = self._cache[i]
        return color.clone(), depth.clone()  # callers may write into their images; the cache stays intact


def open_synthetic(name: str = "room", **options) -> SyntheticRoom:
    if name != "room":
        raise DatasetError(f"unknown synthetic scene {name!r}; available: 'room'")
    return SyntheticRoom(**options)
