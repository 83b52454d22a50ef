"""Plain folder layout for your own RGB-D captures.

```
my_capture/
  intrinsics.json        required: {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5,
                                    "cy": 239.5, "depth_scale": 1000.0}   (metres = png value / depth_scale;
                                    depth_scale defaults to 1000, i.e. millimetres)
  color/000000.png       colour images, .png or .jpg (a folder named rgb/ works too)
                         Colour and depth from two cameras: the numbers above are the depth camera's, and a
                         "color": {"fx", "fy", "cx", "cy"[, "width", "height", "T_color_depth", "poses_of"]}
                         block gives the colour camera; depth is registered into it as frames are read
                         (see registration.py; `eligsir calibrate-color` can estimate and write the block)
  depth/000000.png       16-bit single-channel PNG depth, 0 = no measurement, same size as colour (or as the
                         depth camera of a "color" block)
  poses.txt              optional: camera-to-world poses, TUM format `timestamp tx ty tz qx qy qz qw`,
                         one line per frame in frame order ('#' comments allowed)
  poses/000000.txt       optional alternative: one camera-to-world 4x4 matrix per frame (4 lines of 4 numbers)
  timestamps.txt         optional: one timestamp in seconds per line, one line per frame
```
Colour and depth are paired by file stem when both folders hold the same stems (``000001.jpg`` with
``000001.png``), otherwise by sorted file name, which needs equal counts. Poses use the OpenCV camera axes
(x right, y down, z forward). Timestamps come from ``timestamps.txt``, else from the first column of
``poses.txt``, else index / fps (``fps=30``); they must increase strictly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import DatasetError, RGBDSequence, check_increasing, read_color_sidecar, read_intrinsics_json, \
    read_matrix_file, read_table, read_tum_trajectory

COLOR_DIRS = ("color", "rgb")
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}


def _color_dir(path: Path) -> Path | None:
    return next((path / d for d in COLOR_DIRS if (path / d).is_dir()), None)


def detect(path: Path) -> bool:
    return _color_dir(path) is not None and (path / "depth").is_dir()


def _images(folder: Path, suffixes: set[str]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def _pair(a: list[Path], b: list[Path], what_a: str, what_b: str) -> list[Path]:
    """Files of ``b`` matched to each file of ``a``: by stem when the stems agree, else by sorted order."""
    by_stem = {p.stem: p for p in b}
    if len(by_stem) == len(b) and all(p.stem in by_stem for p in a):
        return [by_stem[p.stem] for p in a]
    if len(a) != len(b):
        lonely = next((p.name for p in a if p.stem not in by_stem), a[0].name if a else "?")
        raise DatasetError(f"{len(a)} {what_a} but {len(b)} {what_b}, and their file names do not match "
                           f"(no {what_b} named like {lonely})")
    return b


def open_folder(path: Path, *, fps: float = 30.0, depth_scale: float | None = None) -> RGBDSequence:
    """Open a plain ``color/ + depth/ + intrinsics.json`` folder (see the module docstring)."""
    if not fps > 0:
        raise DatasetError(f"fps must be positive, got {fps}")
    sidecar = path / "intrinsics.json"
    if not sidecar.is_file():
        raise DatasetError(f"{path}: a color/ + depth/ folder needs an intrinsics.json "
                           f"(width, height, fx, fy, cx, cy, depth_scale)")
    camera, scale = read_intrinsics_json(sidecar)
    color_dir = _color_dir(path)
    colors = _images(color_dir, IMAGE_SUFFIXES)
    if not colors:
        raise DatasetError(f"{color_dir}: no .png or .jpg images (empty sequence)")
    depths = _pair(colors, _images(path / "depth", {".png"}), f"colour images in {color_dir}",
                   f"depth PNGs in {path / 'depth'}")

    timestamps, poses = None, None
    if (path / "poses.txt").is_file():
        pose_t, poses = read_tum_trajectory(path / "poses.txt")
        if len(poses) != len(colors):
            raise DatasetError(f"{path / 'poses.txt'}: {len(poses)} poses for {len(colors)} frames "
                               f"(one line per frame, in frame order)")
        timestamps = pose_t
    elif (path / "poses").is_dir():
        files = _pair(colors, sorted((path / "poses").glob("*.txt")), f"colour images in {color_dir}",
                      f"pose files in {path / 'poses'}")
        poses = [read_matrix_file(f) for f in files]
    if (path / "timestamps.txt").is_file():
        rows = read_table(path / "timestamps.txt", 1)
        timestamps = np.array([float(f[0]) for _, f in rows])
        check_increasing(path / "timestamps.txt", [n for n, _ in rows], timestamps)
        if len(timestamps) != len(colors):
            raise DatasetError(f"{path / 'timestamps.txt'}: {len(timestamps)} timestamps for {len(colors)} frames")
    if timestamps is None:
        timestamps = np.arange(len(colors)) / fps
    if depth_scale is None:
        depth_scale = 1000.0 if scale is None else scale
    return RGBDSequence(name=path.resolve().name, path=path, camera=camera, depth_scale=depth_scale,
                        timestamps=timestamps, poses=poses, color_paths=colors, depth_paths=depths, format="folder",
                        **read_color_sidecar(sidecar, camera))
