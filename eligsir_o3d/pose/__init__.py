"""Pose sources: where each frame's camera-to-world pose comes from, and how good a trajectory is.

``get_pose_source(spec)`` builds one from a short name or a path:

=================  =========================================================================  ==========
spec               source                                                                     causal
=================  =========================================================================  ==========
``gt``             the dataset's own poses (ground truth)                                     yes
``odometry``       Open3D RGB-D odometry, frame-to-model against a small TSDF (odometry.py)   yes
``kiss-icp``       kiss-icp frame-to-map ICP on depth points (kiss.py; needs kiss-icp)       yes
``colmap``         pycolmap SfM over the colour images, scaled by depth (colmap.py)           no: runs in
                                                                                              ``prepare``,
                                                                                              before mapping
a file path        a TUM trajectory file, matched by timestamp (trajectory.py)                yes
a folder path      an existing COLMAP model (cameras/images/points3D .bin or .txt)            no
=================  =========================================================================  ==========

Use: ``src.prepare(sequence)`` once, then ``T_world_cam = src.track(index, timestamp, color, depth, camera,
gt_pose=None)`` per frame in order; ``TrackingLost`` means "no pose for this frame" (skip it; online sources
keep their state and try the next frame against the last good one); ``src.seconds`` / ``src.cpu_seconds`` is
the time spent, which counts toward mapping time in real-time replay.

Map frame: tracked sources start at ``gt_pose`` when it is passed with the first frame (so a map built from
tracked poses lives in the ground truth's frame, and held-out views can be rendered at their ground-truth
poses, off only by the tracking drift), else at the identity. Where the frames differ (no anchor, or a
trajectory file from elsewhere), ``trajectory_accuracy(est, gt, return_alignment=True)["T_gt_est"]`` is the rigid
Umeyama alignment; ``inv(T_gt_est) @ T_gt`` brings a ground-truth pose into the map's frame.

Each source's measured accuracy and time: docs/lab/measurements.md ("Pose sources").
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

POSE_SOURCES = ("gt", "odometry", "kiss-icp", "colmap")

_NAMES = {  # name -> the submodule that defines it, loaded on first use (pose.loop_worker's process has no torch)
    "plot_trajectories": "accuracy", "trajectory_accuracy": "accuracy", "umeyama_alignment": "accuracy",
    "PoseSource": "base", "TrackingLost": "base", "GroundTruthSource": "trajectory", "TrajectoryError": "trajectory",
    "TrajectoryFileSource": "trajectory", "read_tum_trajectory": "trajectory", "write_tum_trajectory": "trajectory"}

__all__ = ["PoseSource", "TrackingLost", "TrajectoryError", "get_pose_source", "read_tum_trajectory", "write_tum_trajectory",
           "trajectory_accuracy", "umeyama_alignment", "plot_trajectories", "POSE_SOURCES"]


def __getattr__(name: str):
    if name not in _NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_NAMES))


def is_colmap_model(path: Path) -> bool:
    """A folder holding a COLMAP sparse model (binary or text), directly or in ``sparse/0`` or ``0``."""
    from .colmap import find_model_dir

    return find_model_dir(path) is not None


def get_pose_source(spec: str | Path, *, sequence: Any = None, **options: Any) -> PoseSource:
    """A pose source from a name (``gt``, ``odometry``, ``kiss-icp``, ``colmap``) or a path.

    Args:
        spec: ``gt`` (the recording's poses), ``odometry`` (Open3D RGB-D odometry), ``kiss-icp``, ``colmap``, a TUM
            trajectory file, or a folder holding a COLMAP model.
        sequence: the sequence the source will track, kept for ``prepare()``.
        **options: passed to the source's constructor (see each class).

    Returns:
        A :class:`PoseSource`. Call ``src.prepare(sequence)`` once before the first ``track``: offline sources
        (colmap) do their work there. ``track(index, timestamp, color, depth, camera)`` returns ``T_world_cam``
        (camera-to-world [4, 4], metres) or raises :class:`TrackingLost`.

    Raises:
        ValueError: an unknown name, or a path that is neither a trajectory file nor a COLMAP model.

    Example:
        ```python
        from eligsir_o3d.datasets import open_sequence
        from eligsir_o3d.pose import get_pose_source

        seq = open_sequence("synthetic", n_frames=4, width=160, height=120)
        src = get_pose_source("gt", sequence=seq)
        src.prepare(seq)
        print(type(src).__name__)  # GroundTruthSource
        ```
    """
    from .trajectory import GroundTruthSource, TrajectoryFileSource

    key = str(spec).strip()
    low = key.lower()
    if low in ("gt", "groundtruth", "ground-truth", "ground_truth"):
        return GroundTruthSource(sequence=sequence, **options)
    if low in ("odometry", "o3d", "open3d"):
        from .odometry import OdometrySource

        return OdometrySource(sequence=sequence, **options)
    if low in ("kiss-icp", "kiss_icp", "kiss", "kissicp"):
        from .kiss import KissICPSource

        return KissICPSource(sequence=sequence, **options)
    if low in ("colmap", "pycolmap", "sfm"):
        from .colmap import ColmapSource

        return ColmapSource(sequence=sequence, **options)
    path = Path(key).expanduser()
    if path.is_dir():
        if not is_colmap_model(path):
            raise ValueError(f"pose source {key!r}: folder holds no COLMAP model (cameras, images and points3D "
                             f".bin or .txt, directly or under sparse/0)")
        from .colmap import ColmapSource

        return ColmapSource(sequence=sequence, model=path, **options)
    if path.is_file():
        return TrajectoryFileSource(path, sequence=sequence, **options)
    raise ValueError(f"unknown pose source {key!r}: use one of {', '.join(POSE_SOURCES)}, a TUM trajectory file "
                     f"or a COLMAP model folder (no such file or folder: {path})")
