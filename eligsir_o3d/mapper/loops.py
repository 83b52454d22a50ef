"""The map's side of loop closure (:mod:`eligsir_o3d.pose.loop_closure`): a Reconstructor's tracked poses go
through its ``rec.loops`` policy, and after a pose-graph optimisation the map follows the corrected keyframes
(anchored Gaussians and retained views move). The time is the ``loops`` stage's and counts as tracking."""

from __future__ import annotations

import time
from contextlib import contextmanager

import numpy as np


def track_corrected(rec, frame, T_raw: np.ndarray) -> np.ndarray:
    """A Reconstructor's tracked pose ``T_raw`` of ``frame`` through its loop closure ``rec.loops``: the
    corrected pose; after an optimisation the map follows (anchored Gaussians and retained views move). The time
    is the ``loops`` stage's and counts as tracking; new Gaussians are anchored to the current keyframe."""
    with _loops_stage(rec):
        T = rec.loops.on_frame(frame.index, T_raw, frame.depth, frame.camera)
        _follow(rec)
    return T


def loads_to_loops(rec, backlog: int) -> None:
    """The stream's backlog to a Reconstructor's loop closure (its worker process is stopped while the mapper is
    behind: :meth:`~eligsir_o3d.pose.loop_closure.LoopClosure.set_load`); nothing without loop closure."""
    if rec.loops is not None:
        rec.loops.set_load(backlog)


def finish_loops(rec) -> None:
    """At the end of a Reconstructor's stream: its loop closure's last background verification taken
    (:meth:`~eligsir_o3d.pose.loop_closure.LoopClosure.finish`, which also ends the worker process) and the map
    moved where it closed a loop; nothing without loop closure."""
    if rec.loops is None:
        return
    with _loops_stage(rec):
        rec.loops.finish()
        _follow(rec)


@contextmanager
def _loops_stage(rec):
    """Time the block as the ``loops`` stage, counted as tracking time."""
    t0 = time.perf_counter()
    try:
        with rec.timing("loops"):
            yield
    finally:
        rec.stats.tracking_s += time.perf_counter() - t0


def _follow(rec) -> None:
    """The map follows the keyframes the last optimisation moved; new Gaussians anchor to the current keyframe."""
    from ..core.anchors import move_anchored

    moves = rec.loops.take_moves()
    if moves:
        move_anchored(rec.gmap, moves)
        for view in rec.views.views:
            view.T_world_cam = rec.loops.pose_of(view.index, view.T_world_cam)
        rec.views.poses_moved()
    rec.gmap.anchor_view = rec.loops.anchor
