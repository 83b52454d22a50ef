"""The PoseSource interface: where a frame's camera-to-world pose comes from when the caller does not give one.

A source is a small long-lived object. ``prepare(sequence)`` is called once before the first frame (offline
sources such as COLMAP do all their work there; online sources only reset). ``track(...)`` is called once per
frame, in order, with only that frame's data: online sources (``causal = True``) see nothing from the future.
``seconds`` accumulates the wall time spent inside ``track`` (and ``prepare``), which the pipeline counts toward
mapping time in real-time replay.

A source that cannot pose a frame raises :class:`TrackingLost` with the frame index and the reason instead of
returning a guess. Online sources keep their last good state after a loss: the next frame is tracked against it.

Map frame of online sources: the first tracked frame defines it. Its pose is ``gt_pose`` when the caller passes
one with the first frame (so a tracked map lives in the ground truth's frame and held-out views can be rendered
at their ground-truth poses), otherwise the identity.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from typing import Any

import numpy as np
import torch

from ..core.camera import Camera, check_pose


class TrackingLost(RuntimeError):
    """A pose source could not pose a frame. The message starts with ``frame <index>:`` and says why."""


class PoseSource(ABC):
    """Base class: subclasses set ``name``/``causal`` and implement ``_track`` (and ``_prepare`` if offline)."""

    name: str = "pose source"
    causal: bool = True  # False: the source uses the whole recorded sequence before mapping starts
    drifts: bool = False  # True: a tracker whose error grows along the run (loop closure is on by default)

    def __init__(self, sequence: Any = None) -> None:
        self.sequence = sequence
        self.seconds = 0.0  # wall time spent in prepare() and track()
        self.cpu_seconds = 0.0  # process CPU time (all threads) in the same calls: a load-independent cost
        self.frames_tracked = 0
        self.frames_lost = 0

    # -- public verbs ----------------------------------------------------------------------------------------
    def prepare(self, sequence: Any = None) -> None:
        """Reset state and, for offline sources, compute the poses of ``sequence`` (default: the one given at
        construction). Cheap for online sources."""
        if sequence is not None:
            self.sequence = sequence
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            self._prepare(self.sequence)
        finally:
            self.seconds += time.perf_counter() - t0
            self.cpu_seconds += time.process_time() - c0

    def check_frames(self, sequence: Any, indices) -> None:
        """Raise ValueError, before mapping starts, when this source cannot pose the frames ``indices`` of
        ``sequence`` at all (a trajectory file that ends before them). Default: nothing to check; a frame the
        source fails on later raises :class:`TrackingLost` and is skipped."""

    def track(self, index: int, timestamp: float, color: torch.Tensor, depth: torch.Tensor, camera: Camera,
              gt_pose: np.ndarray | None = None) -> np.ndarray:
        """Camera-to-world pose [4, 4] float64 of one frame.

        color: [H, W, 3] float in [0, 1]; depth: [H, W] float metres (0 = no measurement); camera: intrinsics of
        that grid; gt_pose: the ground-truth pose when known (used only to anchor the first frame's pose, and by
        the ground-truth source). Raises TrackingLost when the frame cannot be posed.
        """
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            T = self._track(int(index), float(timestamp), color, depth, camera, gt_pose)
            T = check_pose(T, f"frame {index}: pose from {self.name}")
        except TrackingLost:
            self.frames_lost += 1
            raise
        finally:
            self.seconds += time.perf_counter() - t0
            self.cpu_seconds += time.process_time() - c0
        self.frames_tracked += 1
        return T

    @property
    def ms_per_frame(self) -> float:
        """Mean wall time per tracked (or lost) frame, prepare() included."""
        n = self.frames_tracked + self.frames_lost
        return 1000.0 * self.seconds / n if n else 0.0

    @property
    def cpu_ms_per_frame(self) -> float:
        """Mean process CPU time per frame: on an idle machine the wall time is at most this."""
        n = self.frames_tracked + self.frames_lost
        return 1000.0 * self.cpu_seconds / n if n else 0.0

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, causal={self.causal})"

    # -- for subclasses ---------------------------------------------------------------------------------------
    def _prepare(self, sequence: Any) -> None:
        pass

    @abstractmethod
    def _track(self, index: int, timestamp: float, color: torch.Tensor, depth: torch.Tensor, camera: Camera,
               gt_pose: np.ndarray | None) -> np.ndarray:
        """The pose T_world_cam of one frame (the source's own work; ``track`` adds timing and validation)."""
        raise NotImplementedError


def first_pose(gt_pose: np.ndarray | None) -> np.ndarray:
    """Pose of an online source's first frame: the ground truth when given (map frame = ground-truth frame)."""
    return np.eye(4) if gt_pose is None else check_pose(gt_pose, "first frame: gt_pose").copy()


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation block projected onto SO(3) (float32 solvers leave ~1e-4 errors that compound)."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    T[:3, :3] = R
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def as_float_tensor(x: torch.Tensor | np.ndarray, what: str, index: int) -> torch.Tensor:
    """A torch or numpy image as a contiguous float32 CPU tensor; ValueError if it holds NaN or Inf."""
    x = torch.as_tensor(x).detach().to("cpu", torch.float32).contiguous()
    if not math.isfinite(float(x.sum(dtype=torch.float64))):  # a sum is finite iff every entry is
        raise ValueError(f"frame {index}: {what} contains NaN or Inf")
    return x


def check_jump(index: int, T_prev: np.ndarray, T_new: np.ndarray, dt: float, *, max_speed: float,
               max_angular_speed_deg: float, name: str) -> None:
    """Raise TrackingLost when the motion between two poses is faster than a hand-held camera moves.

    Limits are speeds (m/s, deg/s) times the time between the frames (at least one 30 Hz frame period), so a
    dropped frame does not trip them.
    """
    dt = max(float(dt), 1.0 / 30.0) if np.isfinite(dt) and dt > 0 else 1.0 / 30.0
    delta = np.linalg.inv(T_prev) @ T_new
    dist = float(np.linalg.norm(delta[:3, 3]))
    c = np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.degrees(np.arccos(c)))
    if dist > max_speed * dt:
        raise TrackingLost(f"frame {index}: {name} estimate jumps {dist:.3f} m in {dt:.3f} s (limit "
                           f"{max_speed:g} m/s): implausible motion, rejected")
    if angle > max_angular_speed_deg * dt:
        raise TrackingLost(f"frame {index}: {name} estimate turns {angle:.1f} deg in {dt:.3f} s (limit "
                           f"{max_angular_speed_deg:g} deg/s): implausible motion, rejected")
