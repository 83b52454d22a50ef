"""The pose source of a run (ground truth, a tracker, or a trajectory file) and the accuracy of what it tracked."""

from __future__ import annotations

import logging
from pathlib import Path

from .options import RunOptions

log = logging.getLogger("eligsir_o3d")


def pose_source_name(spec: str, seq) -> str:
    """The pose source a run uses: ``spec``, or the reader's default for a recording without poses (a bag)."""
    if spec == "gt" and seq.poses is None and getattr(seq, "default_pose", None):
        return seq.default_pose
    return spec


def prepare_pose_source(spec: str, seq, frames: list[int]):
    """The prepared pose source of a run (None: the sequence's ground truth), checked against its source frames."""
    if pose_source_name(spec, seq) != spec:  # e.g. a bag without poses
        log.info("%s has no poses: tracking with the %s pose source", seq.path, seq.default_pose)
        spec = seq.default_pose
    if spec == "gt":
        if seq.poses is None:
            raise ValueError(f"{seq.path}: the sequence has no ground-truth poses; choose --pose odometry|kiss-icp|colmap")
        return None
    from ..pose import get_pose_source

    src = get_pose_source(spec, sequence=seq)
    src.prepare(seq)
    src.check_frames(seq, frames)  # e.g. a trajectory file that ends before the source frames: an error up front
    return src


def trajectory_accuracy_of(seq, trajectory: dict, out: Path, opts: RunOptions, outputs) -> dict:
    """ATE/RPE of the tracked source trajectory against the sequence's ground truth, and a top-view plot."""
    if seq.poses is None or len(trajectory) < 3:
        return {}
    from ..pose import plot_trajectories, trajectory_accuracy

    est = {ts: T for ts, T in trajectory.values()}
    gt = {float(seq.timestamps[i]): seq.poses[i] for i in trajectory}
    acc = trajectory_accuracy(est, gt, return_alignment=True)
    if opts.plots:
        outputs.stage(out / "trajectory_topview.png", plot_trajectories, out / "trajectory_topview.png",
                      {"gt": gt, opts.pose: est}, reference="gt", title=f"ATE {acc['ate_rmse_m'] * 100:.2f} cm")
    return acc


def loop_closed(seq, trajectory: dict, loops) -> dict:
    """The run's trajectory (``{index: (timestamp, T)}`` as integrated) at the loop closure's final poses; with
    ground truth, ``loops.summary`` gets the ATE of the tracker's own poses, of the poses as integrated (corrected
    online) and of the final ones. Without loop closure, the trajectory as it is."""
    if loops is None:
        return trajectory
    closed = {i: (ts, loops.pose_of(i, T)) for i, (ts, T) in trajectory.items()}
    if seq.poses is not None and len(trajectory) >= 3:
        from ..pose import trajectory_accuracy

        gt = {float(seq.timestamps[i]): seq.poses[i] for i in trajectory}
        ate = lambda traj: trajectory_accuracy({ts: T for ts, T in traj}, gt)["ate_rmse_m"]  # noqa: E731
        loops.summary = {"ate_tracker_m": ate((ts, loops.raw_pose_of(i, T)) for i, (ts, T) in trajectory.items()),
                         "ate_online_m": ate(trajectory.values()), "ate_after_m": ate(closed.values())}
    return closed
