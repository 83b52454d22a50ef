"""TUM RGB-D benchmark layout: ``rgb.txt``, ``depth.txt`` (``timestamp filename``), optional ``groundtruth.txt``.

Colour and depth are paired by nearest timestamp, greedily and one-to-one, as TUM's ``associate.py`` does
(pairs closer than ``max_dt``, default 0.02 s); each pair's pose is the ground-truth sample nearest the colour
timestamp within ``max_dt``. Colour frames left without depth or pose are dropped (``seq.dropped_unassociated``),
never returned with a None pose: a sequence with a ``groundtruth.txt`` always has a pose per frame.

Intrinsics and depth scale, first match wins:
1. an ``intrinsics.json`` sidecar in the folder (width, height, fx, fy, cx, cy, depth_scale); when colour and
   depth come from two cameras, those are the depth camera's and a ``color`` block gives the colour camera
   (depth is then registered into it as frames are read; see :mod:`.registration`);
2. ``camera="fr1" | "fr2" | "fr3" | "default"`` given to :func:`open_sequence`;
3. the freiburg camera named in the folder name (``rgbd_dataset_freiburg2_desk`` -> fr2; also ``fr3_...``);
4. otherwise the OpenNI default (fx = fy = 525, cx = 319.5, cy = 239.5), with a warning.
The depth scale is 5000 (TUM's PNGs store 0.2 mm units) unless the sidecar or ``depth_scale=`` says otherwise.
The published fr1/fr2 intrinsics come with lens distortion that this reader does not undo (most SLAM
evaluations ignore it too); fr3 images are already undistorted.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..core.camera import Camera
from .base import DatasetError, RGBDSequence, check_increasing, read_color_sidecar, read_intrinsics_json, \
    read_table, read_tum_trajectory

# Published TUM RGB-D colour-camera intrinsics (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
TUM_CAMERAS = {
    "fr1": Camera(640, 480, 517.3, 516.5, 318.6, 255.3),
    "fr2": Camera(640, 480, 520.9, 521.0, 325.1, 249.7),
    "fr3": Camera(640, 480, 535.4, 539.2, 320.1, 247.6),
    "default": Camera(640, 480, 525.0, 525.0, 319.5, 239.5),
}
TUM_DEPTH_SCALE = 5000.0


def detect(path: Path) -> bool:
    # present, whatever they are: a list that is not a regular file is refused by name when read, not taken
    # for another layout
    return os.path.lexists(path / "rgb.txt") and os.path.lexists(path / "depth.txt")


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """One-to-one nearest-timestamp pairs (i, j) with |a_i - b_j| < max_dt, as TUM's associate.py, sorted by i.

    Candidate pairs are taken closest first, and each index is used at most once.
    """
    b_sorted = np.argsort(stamps_b)
    b = stamps_b[b_sorted]
    lo = np.searchsorted(b, stamps_a - max_dt, side="left")
    hi = np.searchsorted(b, stamps_a + max_dt, side="right")
    candidates = []
    for i, (l, h) in enumerate(zip(lo, hi)):
        for k in range(l, h):
            d = abs(stamps_a[i] - b[k])
            if d < max_dt:
                candidates.append((d, i, int(b_sorted[k])))
    candidates.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def nearest(stamps: np.ndarray, queries: np.ndarray, max_dt: float) -> np.ndarray:
    """Index into sorted ``stamps`` of the nearest sample to each query, -1 where none is closer than max_dt."""
    right = np.clip(np.searchsorted(stamps, queries), 1, len(stamps) - 1) if len(stamps) > 1 else \
        np.zeros(len(queries), dtype=np.int64)
    left = np.maximum(right - 1, 0)
    pick = np.where(np.abs(stamps[left] - queries) <= np.abs(stamps[right] - queries), left, right)
    return np.where(np.abs(stamps[pick] - queries) < max_dt, pick, -1)


def _read_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    rows = read_table(path, 2, text_fields=1)
    stamps = [float(f[0]) for _, f in rows]
    check_increasing(path, [n for n, _ in rows], stamps)
    return np.array(stamps, dtype=np.float64), [path.parent / f[1] for _, f in rows]


def _camera_from_name(path: Path) -> str | None:
    m = re.search(r"(?:freiburg|fr)([123])(?![0-9])", path.resolve().name.lower())
    return f"fr{m.group(1)}" if m else None


def open_tum(path: Path, *, max_dt: float = 0.02, camera: str | None = None,
             depth_scale: float | None = None) -> RGBDSequence:
    """Open a TUM RGB-D sequence folder (see the module docstring for the rules)."""
    if not max_dt > 0:
        raise DatasetError(f"max_dt must be positive, got {max_dt}")
    rgb_t, rgb_files = _read_list(path / "rgb.txt")
    depth_t, depth_files = _read_list(path / "depth.txt")
    pairs = associate(rgb_t, depth_t, max_dt)
    no_depth = len(rgb_t) - len(pairs)

    poses, no_pose = None, 0
    gt_file = path / "groundtruth.txt"
    if os.path.lexists(gt_file):  # a link to a device or a folder there is refused by name, not ignored
        gt_t, gt_poses = read_tum_trajectory(gt_file)
        k = nearest(gt_t, rgb_t[[i for i, _ in pairs]], max_dt)
        no_pose = int((k < 0).sum())
        pairs = [p for p, kk in zip(pairs, k) if kk >= 0]
        poses = [gt_poses[kk] for kk in k if kk >= 0]
    dropped = no_depth + no_pose
    if not pairs:
        raise DatasetError(f"{path}: no frame left after associating colour with depth"
                           f"{' and ground truth' if poses is not None else ''} within max_dt={max_dt} s "
                           f"({len(rgb_t)} colour, {len(depth_t)} depth timestamps; try a larger max_dt)")
    if dropped:
        warnings.warn(f"{path.name}: dropped {dropped} of {len(rgb_t)} colour frames ({no_depth} without depth, "
                      f"{no_pose} without a ground-truth pose within {max_dt} s)", stacklevel=3)

    cam, scale = _intrinsics(path, camera)
    two = read_color_sidecar(path / "intrinsics.json", cam) if (path / "intrinsics.json").is_file() else {}
    return RGBDSequence(name=path.resolve().name, path=path, camera=cam, **two,
                        depth_scale=depth_scale if depth_scale is not None else scale,
                        timestamps=rgb_t[[i for i, _ in pairs]], poses=poses,
                        color_paths=[rgb_files[i] for i, _ in pairs], depth_paths=[depth_files[j] for _, j in pairs],
                        dropped_unassociated=dropped, format="tum")


def _intrinsics(path: Path, camera: str | None) -> tuple[Camera, float]:
    sidecar = path / "intrinsics.json"
    if sidecar.is_file():
        cam, scale = read_intrinsics_json(sidecar)
        return cam, TUM_DEPTH_SCALE if scale is None else scale
    if camera is not None and camera not in TUM_CAMERAS:
        raise DatasetError(f"unknown TUM camera {camera!r}; choose one of {', '.join(TUM_CAMERAS)}")
    key = camera or _camera_from_name(path)
    if key is None:
        warnings.warn(f"{path.name}: no intrinsics.json and no freiburg1/2/3 in the folder name; using the OpenNI "
                      f"default intrinsics (fx=fy=525, cx=319.5, cy=239.5). Pass camera='fr1'|'fr2'|'fr3' or add "
                      f"an intrinsics.json to choose.", stacklevel=4)
        key = "default"
    return TUM_CAMERAS[key], TUM_DEPTH_SCALE
