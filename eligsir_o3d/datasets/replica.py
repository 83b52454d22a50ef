"""Replica as rendered for NICE-SLAM / iMAP (the layout SplaTAM and Gaussian-SLAM read too).

```
office0/
  results/frame000000.jpg ...   colour
  results/depth000000.png ...   16-bit depth, metres = value / scale
  traj.txt                      one camera-to-world 4x4 per line, row-major (16 numbers), one line per frame
  cam_params.json               {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}} (here or in the parent folder)
```
Frames are matched by sorted file name; timestamps are index / fps (``fps=30``). Without a cam_params.json (or an
``intrinsics.json`` sidecar, which wins) the NICE-SLAM Replica values are used with a warning:
1200x680, fx = fy = 600, cx = 599.5, cy = 339.5, scale 6553.5.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..core.camera import Camera
from ..io.inputs import read_json
from .base import DatasetError, RGBDSequence, read_intrinsics_json, read_matrix_rows

REPLICA_CAMERA = Camera(1200, 680, 600.0, 600.0, 599.5, 339.5)
REPLICA_DEPTH_SCALE = 6553.5


def detect(path: Path) -> bool:
    results = path / "results"
    return (path / "traj.txt").is_file() and results.is_dir() and any(results.glob("frame*.jpg"))


def _cam_params(path: Path) -> tuple[Camera, float]:
    sidecar = path / "intrinsics.json"
    if sidecar.is_file():
        cam, scale = read_intrinsics_json(sidecar)
        return cam, REPLICA_DEPTH_SCALE if scale is None else scale
    for f in (path / "cam_params.json", path.parent / "cam_params.json"):
        if f.is_file():
            try:
                c = read_json(f, "camera parameters", error=DatasetError)["camera"]
                return Camera(int(c["w"]), int(c["h"]), float(c["fx"]), float(c["fy"]), float(c["cx"]),
                              float(c["cy"])), float(c["scale"])
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise DatasetError(f"{f}: expected {{'camera': {{'w', 'h', 'fx', 'fy', 'cx', 'cy', 'scale'}}}} "
                                   f"({type(e).__name__}: {e})") from None
    warnings.warn(f"{path.name}: no cam_params.json here or in the parent folder; using the NICE-SLAM Replica "
                  f"camera (1200x680, fx=fy=600, cx=599.5, cy=339.5, scale 6553.5)", stacklevel=4)
    return REPLICA_CAMERA, REPLICA_DEPTH_SCALE


def open_replica(path: Path, *, fps: float = 30.0, depth_scale: float | None = None) -> RGBDSequence:
    """Open a NICE-SLAM style Replica scene folder."""
    if not fps > 0:
        raise DatasetError(f"fps must be positive, got {fps}")
    colors = sorted((path / "results").glob("frame*.jpg"))
    depths = sorted((path / "results").glob("depth*.png"))
    if len(colors) != len(depths):
        raise DatasetError(f"{path / 'results'}: {len(colors)} frame*.jpg but {len(depths)} depth*.png files")
    poses = read_matrix_rows(path / "traj.txt")
    if len(poses) != len(colors):
        raise DatasetError(f"{path / 'traj.txt'}: {len(poses)} poses for {len(colors)} frames (one line per frame)")
    cam, scale = _cam_params(path)
    return RGBDSequence(name=path.resolve().name, path=path, camera=cam,
                        depth_scale=scale if depth_scale is None else depth_scale,
                        timestamps=np.arange(len(colors)) / fps, poses=poses, color_paths=colors, depth_paths=depths,
                        format="replica")
