"""Poses given, not estimated: the dataset's ground truth, or a TUM-format trajectory file.

TUM format (Sturm et al. 2012): one pose per line, ``timestamp tx ty tz qx qy qz qw``, camera-to-world,
``#`` comments. ORB-SLAM3, evo and this package (``trajectory.txt`` in a results folder) write it. A frame is
given the pose whose timestamp is nearest to the frame's, if it lies within ``max_diff`` seconds; otherwise the
source raises TrackingLost for that frame (the file has no pose for it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import check_pose, pose_to_tum
from ..datasets.base import read_tum_trajectory  # noqa: F401 (the one TUM reader, exported with the writer)
from .base import PoseSource, TrackingLost


class TrajectoryError(ValueError):
    """A trajectory file that cannot pose the frames it is given for (names the file and the frames)."""


def write_tum_trajectory(path: str | Path, timestamps: Sequence[float], poses: Sequence[np.ndarray]) -> Path:
    """Write camera-to-world poses as a TUM trajectory file (creating parent folders)."""
    if len(timestamps) != len(poses):
        raise ValueError(f"write_tum_trajectory: {len(timestamps)} timestamps for {len(poses)} poses")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, metres, OpenCV camera axes)"]
    for t, T in zip(timestamps, poses):
        p, q = pose_to_tum(check_pose(T, f"pose at t={float(t):.6f}"))
        lines.append(f"{float(t):.6f} " + " ".join(f"{x:.9f}" for x in (*p, *q)))
    from ..io.atomic import atomic_write_text

    return atomic_write_text(path, "\n".join(lines) + "\n")


def nearest_index(stamps: np.ndarray, t: float) -> tuple[int, float]:
    """(index, |difference|) of the sorted ``stamps`` entry nearest to ``t``."""
    i = int(np.searchsorted(stamps, t))
    cands = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    j = min(cands, key=lambda k: abs(stamps[k] - t))
    return j, abs(float(stamps[j]) - t)


class GroundTruthSource(PoseSource):
    """The dataset's own poses: ``gt_pose`` when the caller passes it, else ``sequence.poses[index]``."""

    name = "gt"

    def _prepare(self, sequence) -> None:
        if sequence is not None and getattr(sequence, "poses", None) is None:
            raise ValueError(f"pose source 'gt': sequence {getattr(sequence, 'name', '')!r} has no ground-truth "
                             "poses; use --pose odometry, kiss-icp, colmap or a trajectory file")

    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        if gt_pose is not None:
            return gt_pose
        poses = getattr(self.sequence, "poses", None)
        if poses is None:
            raise ValueError(f"frame {index}: pose source 'gt' got no gt_pose and has no sequence with poses")
        return poses[index]


class TrajectoryFileSource(PoseSource):
    """Poses read from a TUM trajectory file, associated to frames by nearest timestamp (``max_diff`` s)."""

    def __init__(self, path: str | Path, *, max_diff: float = 0.02, sequence=None) -> None:
        super().__init__(sequence)
        self.path = Path(path)
        self.max_diff = float(max_diff)
        self.timestamps, self.poses = read_tum_trajectory(self.path)
        self.name = f"file:{self.path.name}"

    def check_frames(self, sequence, indices) -> None:
        """Raise :class:`TrajectoryError` when frames of ``indices`` lie before the file's first pose or after its
        last one (more than ``max_diff``): the file has fewer poses than the frames to map (a gap inside its span
        is a lost frame, skipped when met)."""
        stamps = np.asarray(getattr(sequence, "timestamps", []), dtype=np.float64)
        idx = [int(i) for i in indices if 0 <= int(i) < len(stamps)]
        if not idx:
            return
        t0, t1 = float(self.timestamps[0]), float(self.timestamps[-1])
        out = [i for i in idx if not t0 - self.max_diff <= stamps[i] <= t1 + self.max_diff]
        if out:
            raise TrajectoryError(
                f"{self.path}: {len(self.poses)} poses for {len(idx)} frames: the trajectory covers t={t0:.3f}-"
                f"{t1:.3f} s but {len(out)} of the frames lie outside it (the first: frame {out[0]} at "
                f"t={stamps[out[0]]:.3f} s); map fewer frames (--max-frames) or give a trajectory of the whole "
                f"sequence")

    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        j, diff = nearest_index(self.timestamps, timestamp)
        if diff > self.max_diff:
            raise TrackingLost(f"frame {index}: {self.path} has no pose within {self.max_diff:g} s of t="
                               f"{timestamp:.6f} (nearest is {diff:.3f} s away)")
        return self.poses[j]
