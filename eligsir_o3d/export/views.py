"""Where a saved map is seen from: the camera and the poses recorded beside it in a results folder, and cameras on
a sphere around a map that has none.

    camera = camera_next_to(Path("runs/kitchen/map.ply")) or DEFAULT_CAMERA      # run.json's camera
    poses = poses_next_to(Path("runs/kitchen/map.ply"))                         # trajectory.txt, or None

Poses are ``T_world_cam`` (camera-to-world, OpenCV axes).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import Camera, look_at

DEFAULT_CAMERA = Camera(640, 480, 525.0, 525.0, 319.5, 239.5)  # the OpenNI / TUM default


def sphere_poses(points: np.ndarray, camera: Camera, n_views: int = 40,
                 margin: float = 1.1) -> tuple[list[np.ndarray], float]:
    """Cameras on a Fibonacci sphere around the bounding box of ``points`` [M, 3], looking at its centre, far
    enough that the box fits the field of view. Returns (poses, the depth range they need)."""
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)  # robust to floaters
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    half_fov = min(math.atan(camera.width / (2 * camera.fx)), math.atan(camera.height / (2 * camera.fy)))
    dist = margin * radius / math.sin(half_fov)
    k = np.arange(n_views) + 0.5
    polar = np.arccos(1 - 2 * k / n_views)
    azimuth = math.pi * (1 + 5 ** 0.5) * k
    dirs = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], -1)
    return [look_at(centre + dist * d, centre) for d in dirs], dist + 2 * radius


def subsample(poses: list[np.ndarray], max_views: int) -> list[np.ndarray]:
    """At most ``max_views`` of ``poses``, evenly spaced along the list, first and last kept."""
    if len(poses) <= max_views:
        return poses
    idx = np.unique(np.linspace(0, len(poses) - 1, max_views).round().astype(int))
    return [poses[i] for i in idx]


def camera_next_to(map_ply: str | Path) -> Camera | None:
    """The camera recorded in a results folder's ``run.json`` (key ``camera``), a ``config.json`` (key ``camera``
    or ``intrinsic``) or ``intrinsics.json`` beside the map, if any."""
    map_ply = Path(map_ply)
    for name in ("run.json", "config.json", "intrinsics.json"):
        f = map_ply.parent / name
        if not f.is_file():
            continue
        try:
            data = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        for cand in (data.get("camera"), data.get("intrinsic"), data) if isinstance(data, dict) else ():
            if isinstance(cand, dict) and all(k in cand for k in ("width", "height", "fx", "fy", "cx", "cy")):
                return Camera(int(cand["width"]), int(cand["height"]), float(cand["fx"]), float(cand["fy"]),
                              float(cand["cx"]), float(cand["cy"]))
    return None


def poses_next_to(map_ply: str | Path, poses: Sequence[np.ndarray] | str | Path | None = None,
                  required: bool = False) -> list[np.ndarray] | None:
    """The views a map was made from, as camera-to-world matrices: ``poses`` as given, read from the TUM file
    ``poses`` names, or read from ``trajectory.txt`` beside ``map_ply``. Without ``poses`` and without that file:
    None, or a ValueError when ``required``; a named file that does not exist is always a ValueError."""
    from ..datasets.base import read_tum_trajectory

    if poses is not None and not isinstance(poses, (str, Path)):
        return list(poses)
    map_ply = Path(map_ply)
    path = Path(poses) if poses is not None else map_ply.parent / "trajectory.txt"
    if not path.is_file():
        if not required and poses is None:
            return None
        raise ValueError(f"{map_ply}: {path} does not exist: the low-pass is baked at the depth the map's views "
                         f"saw each Gaussian (give --poses)")
    return list(read_tum_trajectory(path)[1])
