"""Held-out views of a recording without poses: posed by the run's own pose source, never admitted into the map.

A ROS bag without a pose topic, a phone capture whose tracking was not exported, ``own_capture.py``: such a
recording has no ground truth, so its held-out views have no pose to be rendered at. Rendering them at the
identity (the placeholder every pose-less frame carries) scores the map's error against a camera that never
moved, not the map (lab: tracked-heldout). MonoGS's rule for non-keyframes applies instead: every frame is tracked,
only the map's own frames are mapped. Here the held-out views are tracked by the run's pose source:

- an online (causal) source: a second instance of it tracks the whole recording in order, source and held-out
  frames alike, before mapping starts (evaluation work: its time is not mapping time). The mapper's own
  instance tracks only the source frames, so the held-out views cannot influence the map or its poses.
  At evaluation the held-out poses are moved into the map's frame by one rigid alignment of this evaluation
  trajectory's source poses to the mapper's (refined) source poses, the same rule as for ground truth.
- an offline source (COLMAP, a trajectory file): it has posed every frame already; the held-out views are looked
  up in it.

A view the source cannot pose (``TrackingLost``, an invalid pose) is left out of the evaluation and counted
(``heldout_untracked`` in metrics.json). metrics.json labels the figure: ``heldout_pose_origin`` says
``"tracked by <source> (not mapped)"``.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..run.frame_faults import BAD_FRAME_ERRORS

log = logging.getLogger("eligsir_o3d")


def heldout_pose_label(pose_name: str, tracked: bool) -> str:
    """How the held-out figure's views were posed, as metrics.json and the summary say it."""
    return f"tracked by {pose_name} (not mapped)" if tracked else "ground truth"


class TrackedHeldout:
    """Poses of held-out views from the run's pose source (see the module docstring).

    After :meth:`track`: ``frames`` (the trackable held-out frames, their ``T_world_cam`` set to the tracked
    pose), ``untracked`` (list of {"index", "reason"}), ``source_poses`` (sequence index -> [4, 4] pose of each
    source frame in the same evaluation trajectory; empty for an offline source, whose poses ARE the map's:
    :func:`heldout_into_map_frame` aligns with them),
    ``seconds`` (wall time spent).
    """

    def __init__(self, pose_name: str, run_source, sequence, depth_max: float) -> None:
        self.pose_name, self.run_source, self.seq, self.depth_max = pose_name, run_source, sequence, depth_max
        self.frames: list = []
        self.untracked: list[dict] = []
        self.source_poses: dict[int, np.ndarray] = {}
        self.seconds = 0.0

    def track(self, heldout_frames: list, source: list[int]) -> list:
        """Pose ``heldout_frames`` (Frames read from the sequence); returns the trackable ones."""
        t0 = time.perf_counter()
        try:
            if getattr(self.run_source, "causal", True):
                self._track_online(heldout_frames, source)
            else:
                for f in heldout_frames:
                    self._pose(self.run_source, f)
        finally:
            self.seconds += time.perf_counter() - t0
        if heldout_frames and not self.frames:
            first = self.untracked[0]
            raise ValueError(f"{getattr(self.seq, 'path', 'sequence')}: none of the {len(heldout_frames)} held-out "
                             f"views could be tracked by {self.pose_name} (the first: frame {first['index']}: "
                             f"{first['reason']})")
        log.info("held-out views tracked by %s: %d of %d (%.1f s)", self.pose_name, len(self.frames),
                 len(heldout_frames), self.seconds)
        return self.frames

    def _pose(self, src, frame) -> bool:
        try:
            frame.T_world_cam = src.track(frame.index, frame.timestamp, frame.color, frame.depth, frame.camera)
        except BAD_FRAME_ERRORS as e:
            text = str(e)
            reason = text.split(": ", 1)[1] if text.startswith(f"frame {frame.index}: ") else text
            self.untracked.append({"index": int(frame.index), "reason": reason})
            log.warning("held-out frame %d left out of the evaluation: %s cannot track it: %s", frame.index,
                        self.pose_name, reason)
            return False
        self.frames.append(frame)
        return True

    def _track_online(self, heldout_frames: list, source: list[int]) -> None:
        from ..pose import get_pose_source

        src = get_pose_source(self.pose_name, sequence=self.seq)  # a fresh instance: the mapper's is untouched
        src.prepare(self.seq)
        held = {int(f.index): f for f in heldout_frames}
        for i in sorted(set(source) | set(held)):
            if i in held:
                self._pose(src, held[i])
                continue
            try:
                f = self.seq.frame(i, depth_max=self.depth_max)
                self.source_poses[i] = src.track(i, f.timestamp, f.color, f.depth, f.camera)
            except BAD_FRAME_ERRORS:  # the mapper skips and reports it; here it only is not a reference pose
                continue



def track_heldout(p) -> TrackedHeldout | None:
    """For a :class:`~eligsir_o3d.run.pipeline.MappingPipeline` ``p`` whose recording has no poses but a pose source:
    track its held-out views (``p.heldout_frames`` becomes the trackable ones) and return the tracker; else None."""
    if p.seq.poses is not None or p.pose_source is None or not p.heldout_frames:
        return None
    tracking = TrackedHeldout(p.pose_name, p.pose_source, p.seq, p.config.depth_max)
    p.heldout_frames = tracking.track(p.heldout_frames, p.source)
    return tracking


def heldout_into_map_frame(frames: list, map_poses: dict[int, np.ndarray], reference: dict[int, np.ndarray]) -> None:
    """Express held-out poses (given in the ``reference`` trajectory's frame: the ground truth, or the evaluation
    trajectory of :class:`TrackedHeldout`) in the map's frame, through one rigid alignment of the reference's
    source poses to the mapper's (``map_poses``: sequence index -> [4, 4], refined): the paper's
    "training-pose alignment". Nothing to do with fewer than 3 common frames (an offline source's held-out
    poses are the map's already)."""
    from ..pose.accuracy import pose_alignment

    common = [i for i in map_poses if i in reference]
    if len(common) < 3:
        return
    T_map_ref = np.linalg.inv(pose_alignment([map_poses[i] for i in common], [reference[i] for i in common]))
    for f in frames:
        f.T_world_cam = T_map_ref @ f.T_world_cam
