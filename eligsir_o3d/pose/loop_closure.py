"""Loop closure of a tracked run: keyframes, loop edges and the pose graph, as one policy with explicit state.

The pose source keeps tracking in its own (drifting) frame; this policy keeps, per keyframe, the tracker's pose and
the corrected one. A frame's corrected pose is its tracker pose carried by the correction of its keyframe (the last
keyframe at or before it): ``T = T_corr[k] @ inv(T_raw[k]) @ T_raw``. A new keyframe is placed at once by the
tracker's relative pose from the previous one; its cloud and its odometry edge (information, and for the
``refine_sources`` the edge registered onto the previous keyframe, and the skip edge registered onto the keyframe
two back) are built from its strided depth, in the worker process (``keyframe_worker``) or on the mapper's thread,
and *settle* ``settle_frames`` frames later: the edges enter the graph and the keyframe's correction moves it and
every later keyframe rigidly (the tail keeps its relative poses), so the map follows. The mapper waits for a build
only at its settling frame, so offline runs give the same trajectory wherever the build ran (the process then runs
at the mapper's CPU priority); under the real-time clock (``background``) a keyframe settles as soon as its build
arrives (the process at the lowest, on a quarter of the CPUs, and stopped while the mapper is behind:
:meth:`LoopClosure.set_load`). A settled keyframe looks for loop candidates (:func:`.loops.candidates`) and
verifies at most ``max_candidates`` of them (:func:`.loops.verify`); an accepted loop edge triggers one optimisation
of the settled keyframes' graph (:func:`.pose_graph.optimise`; the unsettled tail moves rigidly with the last
settled keyframe), whose line process may still prune it (then counted as rejected); skip edges not yet optimised
get one more optimisation at :meth:`LoopClosure.finish`. After an optimisation or a settling,
:meth:`LoopClosure.take_moves` hands the caller each keyframe whose corrected pose changed, so the map can follow.

Verification (registration, the expensive part) runs on the mapper's thread, one candidate per frame, or, with
``background``, in the worker process (:mod:`.loop_worker`: no GIL shared with the mapper, lowest CPU priority):
a frame then only submits the next candidate and takes a finished result, so a real-time stream never waits for
a registration, at the price of results arriving a few frames later (when depends on the machine, so background
verification is for real-time runs; replays on a deterministic clock verify on the mapper's thread).
:meth:`LoopClosure.finish` settles the last keyframes, waits for the last verification and ends the process.
Should the process fail to start, die or fall silent, a ``RuntimeWarning`` says so and its work continues on the
mapper's thread (keyframes it was building are built there from the inputs kept until they settle, the candidate
it held is verified there at once; nothing already mapped changes).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import invert_pose, rotation_angle_deg
from .loop_worker import LoopWorker, WorkerFailed
from .loop_keyframes import KeyframeChain
from .loop_state import load_state, state_of
from .loops import Keyframe, LoopConfig, LoopResult, for_source, verify
from .pose_graph import Edge, GraphConfig, odometry_edges, optimise


@dataclass
class LoopClosureConfig:
    """Loop closure of tracked runs: keyframes, loop detection and verification, the pose graph."""

    enabled: str = "auto"
    """auto: on for tracked runs (no poses given), off where poses are given; on | off."""
    detect: LoopConfig = field(default_factory=LoopConfig)
    """Keyframes, loop candidates and their registration test."""
    graph: GraphConfig = field(default_factory=GraphConfig)
    """The pose graph's optimisation."""
    background: str = "auto"
    """Verify loop candidates in a worker process: auto (on under the real-time clock and in live runs), on, off."""
    keyframe_work: str = "process"
    """Where keyframes' clouds and odometry edges are built: process (the worker process), inline (mapper thread)."""
    hold_backlog: int = 2
    """With background: stop the worker process while this many frames wait, until none does (0: never)."""


def loop_closure_for(cfg: LoopClosureConfig, tracked: bool, source=None, realtime: bool = False) -> "LoopClosure | None":
    """The loop-closure policy of a run (None where it is off: poses given, or ``enabled = off``); ``source``:
    the pose source, or its name (``detect.refine_edges = auto`` refines the odometry edges of the
    ``refine_sources``); ``realtime``: the run is on the real-time clock (``background = auto`` verifies in the
    worker process then)."""
    source = getattr(source, "name", source) or ""
    mode, background, work = str(cfg.enabled).lower(), str(cfg.background).lower(), str(cfg.keyframe_work).lower()
    if work not in ("process", "inline"):
        raise ValueError(f"loops.keyframe_work must be process or inline, got {cfg.keyframe_work!r}")
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"loops.enabled must be auto, on or off, got {cfg.enabled!r}")
    if background not in ("auto", "on", "off"):
        raise ValueError(f"loops.background must be auto, on or off, got {cfg.background!r}")
    if mode == "off" or (mode == "auto" and not tracked):
        return None
    background_on = background == "on" or (background == "auto" and realtime)
    return LoopClosure(for_source(cfg.detect, source), cfg.graph, background=background_on,
                       keyframe_worker=work == "process", hold_backlog=int(cfg.hold_backlog))


class LoopClosure(KeyframeChain):
    """Keyframes, loop edges and the pose graph of one tracked run.

    ``on_frame(index, T_raw, depth, camera)`` returns the frame's corrected pose; ``anchor`` is the frame index
    of the current keyframe (the anchor of Gaussians created now); ``take_moves()`` returns ``{keyframe index:
    (old pose, new pose)}`` since the last call; ``pose_of(index, T)`` is the final corrected pose of a frame
    that was given pose ``T`` when it was integrated. ``background``: verify in the worker process and settle
    keyframes as their builds arrive; ``keyframe_worker``: build keyframes in the worker process; ``hold_backlog``:
    see :meth:`set_load`."""

    name = "loop-closure"

    def __init__(self, loops: LoopConfig | None = None, graph: GraphConfig | None = None, *, background: bool = False,
                 keyframe_worker: bool = False, hold_backlog: int = 2):
        self.cfg = loops or LoopConfig()
        self.hold_backlog = int(hold_backlog)
        self.background = bool(background)
        self.keyframe_worker = bool(keyframe_worker)
        self.settled = 0  # keyframes whose cloud and odometry edge are in the graph (the first ``settled``)
        self.inputs: dict[int, tuple] = {}  # unsettled keyframe -> (strided depth, intrinsics), until it settles
        self._submitted = 0  # keyframes the worker holds or builds
        self._rescued: tuple[int, int] | None = None  # the candidate a failed worker held (verified next)
        self._job: tuple[int, int] | None = None  # (keyframe, candidate) the worker process is verifying
        self._worker: LoopWorker | None = None  # made on first use
        self.failure: str | None = None  # why the worker process was given up (then verification is inline)
        self.graph_cfg = graph or GraphConfig()
        self.keys: list[Keyframe] = []
        self.corrected: list[np.ndarray] = []  # per keyframe, T_world_cam after the last optimisation
        self.odo_rel: list[np.ndarray] = []  # per keyframe, its odometry edge T_prev_k (the tracker's, or refined)
        self.odo_info: list[np.ndarray] = []  # per keyframe, the information of its edge from the previous one
        self.loop_edges: list[Edge] = []  # accepted by verification (the graph may prune them)
        self.skip_edges: list[Edge] = []  # keyframe k - 2 -> k registrations (``skip_edges``), certain like odometry
        self._skips_optimised = 0  # skip edges the last optimisation had
        self.pruned: set[tuple[int, int]] = set()
        self.frames: dict[int, tuple[int, np.ndarray]] = {}  # frame index -> (keyframe position, inv(T_k) @ T)
        self.raw: dict[int, np.ndarray] = {}  # frame index -> the tracker's pose
        self.summary: dict = {}  # ATE before and after, where the run has ground truth (run.poses.loop_closed)
        self.counts = {"keyframes": 0, "candidates": 0, "verified": 0, "rejected_registration": 0,
                       "rejected_graph": 0, "accepted": 0, "optimisations": 0, "refined_edges": 0,
                       "skip_edges": 0}
        self.seconds = 0.0  # on the mapper's thread
        self.worker_seconds = 0.0  # verification in the worker process
        self.worker_cpu_seconds = 0.0  # the worker process's CPU time (its own report)
        self.wait_seconds = 0.0  # the mapper's thread waiting for a keyframe's build at its settling frame
        self.held_seconds = 0.0  # the worker process stopped while the mapper was behind (:meth:`set_load`)
        self.keyframe_seconds = 0.0  # building keyframes, wherever it ran
        self.injected: list[tuple[int, np.ndarray]] = []  # test hook: (frame index, wrong T_target_source)
        self.pending: list[tuple[int, int]] = []  # (keyframe, candidate) pairs waiting for verification
        self._moves: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.log: list[dict] = []  # one row per verified candidate

    # ---- per frame ----------------------------------------------------------------------------------------
    def on_frame(self, index: int, T_raw: np.ndarray, depth, camera) -> np.ndarray:
        """The corrected pose of frame ``index`` tracked at ``T_raw``; a new keyframe may close a loop."""
        t0 = time.perf_counter()
        try:
            T_raw = np.asarray(T_raw, dtype=np.float64)
            if self._is_keyframe(index, T_raw):
                self._add_keyframe(index, T_raw, depth, camera)
            self._settle_due(index)
            if self._verify_pending():
                self._optimise()
            k = len(self.keys) - 1
            rel = invert_pose(self.keys[k].raw_pose) @ T_raw
            T = self.corrected[k] @ rel
            self.frames[int(index)] = (k, invert_pose(self.corrected[k]) @ T)
            self.raw[int(index)] = T_raw
            return T
        finally:
            self.seconds += time.perf_counter() - t0

    def set_load(self, backlog: int) -> None:
        """The stream's backlog (frames waiting for the mapper): with ``background``, the worker process is stopped
        while ``hold_backlog`` or more frames wait (0: never) and goes on when none does, so loop closure takes
        no CPU from a mapper that is behind."""
        if not self.background or self._worker is None or self.failure is not None:
            return
        if backlog >= self.hold_backlog > 0:
            self._worker.hold(True)
        elif backlog <= 0:
            self._worker.hold(False)

    def _is_keyframe(self, index: int, T_raw: np.ndarray) -> bool:
        if not self.keys:
            return True
        last = self.keys[-1]
        delta = invert_pose(last.raw_pose) @ T_raw
        c = self.cfg
        return (np.linalg.norm(delta[:3, 3]) >= c.keyframe_dist or rotation_angle_deg(delta[:3, :3]) >=
                c.keyframe_angle_deg or index - last.index >= c.keyframe_every)

    def _verify_pending(self) -> bool:
        """Verify up to ``per_frame`` waiting candidates (a bounded slice of work per frame), or with
        ``background`` take the worker's finished result and hand it the next (should the worker fail, the
        candidate it held is verified here at once); True when one was accepted as a loop edge."""
        found = False
        if self.background and self.failure is None:
            found = self._verify_in_background()
            if self.failure is None:
                return found
        for _ in range(min(self.cfg.per_frame, len(self.pending))):
            k, j = self.pending.pop(0)
            self._rescued = None
            found |= self._take(verify(self.keys, self.corrected, k, j, self.cfg))
        return found

    def _verify_in_background(self, wait: bool = False) -> bool:
        """Take the worker's finished result (``wait``: block for it) and, unless waiting, hand it the next
        candidate; a failed worker is given up (:attr:`failure`). True when a loop edge was accepted."""
        found = False
        try:
            if self._job is not None and (done := self._worker.result(wait)) is not None:
                self.worker_seconds += done[1]
                self.worker_cpu_seconds = self._worker.cpu_seconds
                self._job = None
                found = self._take(done[0])
            if self._job is None and self.pending and not wait:
                self._job = self.pending.pop(0)
                self._get_worker().submit(self.keys, self.corrected, *self._job)
        except WorkerFailed as e:
            self._give_up_worker(str(e))
        return found

    def _give_up_worker(self, why: str) -> None:
        """Verify on the mapper's thread from now on; the candidate the worker held waits first in line."""
        self.failure = f"{why}; keyframes are built and loop candidates verified on the mapper's thread from now on"
        warnings.warn(self.failure, RuntimeWarning, stacklevel=2)
        self.close(kill=True)

    def finish(self) -> None:
        """At the end of the stream: settle the last keyframes (waiting for their builds), wait for a verification
        still in the worker (verified here should the worker fail) and, if it closed a loop, optimise
        (:meth:`take_moves` then has the moves); the worker ends."""
        t0 = time.perf_counter()
        try:
            self._settle_due(None)
            found = False
            if self._job is not None:
                running = self._job
                found = self._verify_in_background(wait=True)
                if self.failure is not None and self.pending[:1] == [running]:
                    found |= self._take(verify(self.keys, self.corrected, *self.pending.pop(0), self.cfg))
            if found or len(self.skip_edges) > self._skips_optimised:
                self._optimise()
        finally:
            self.seconds += time.perf_counter() - t0
            self.close()

    def close(self, kill: bool = False) -> None:
        """End the worker process, if one runs (``kill``: without waiting for it); the candidate it held goes back
        to the front of the queue, the keyframes it was building are built again (from their kept inputs)."""
        if self._job is not None:
            self.pending.insert(0, self._job)
            self._rescued, self._job = self._job, None
        self._submitted = self.settled  # a new worker builds the unsettled keyframes again
        if self._worker is not None:
            self.worker_cpu_seconds = max(self.worker_cpu_seconds, self._worker.cpu_seconds)
            self._worker.close(kill)
            self.held_seconds += self._worker.held_seconds
            self._worker = None

    def _take(self, result: LoopResult) -> bool:
        """Count and log one verification; an accepted one becomes a loop edge (True)."""
        result = self._maybe_injected(result)
        self.counts["verified"] += 1
        self.log.append(_row(result, self.keys))
        if not result.accepted:
            self.counts["rejected_registration"] += 1
            return False
        self.loop_edges.append(Edge(result.source, result.target, result.transform, result.information, True))
        return True

    def _maybe_injected(self, result: LoopResult) -> LoopResult:
        for index, T in self.injected:
            if self.keys[result.source].index >= index and result.accepted:
                self.injected.remove((index, T))
                return dataclasses.replace(result, transform=np.asarray(T, dtype=np.float64))
        return result

    def _optimise(self) -> None:
        """Optimise the settled keyframes' graph; the unsettled ones move rigidly with the last settled one (placed
        again by their tracker edges from it)."""
        s = self.settled
        skips = [e for e in self.skip_edges if e.source < s]
        edges = odometry_edges(self.odo_rel[:s], self.odo_info[:s]) + skips + self.loop_edges
        new, kept = optimise(self.corrected[:s], edges, self.graph_cfg)
        self._skips_optimised = len(skips)
        self.counts["optimisations"] += 1
        self.pruned = {(e.source, e.target) for e, ok in zip(self.loop_edges, kept) if not ok}
        self.counts["accepted"] = sum(kept)
        self.counts["rejected_graph"] = len(self.pruned)
        for k in range(s):
            self._record_move(k, self.corrected[k], new[k])
        self._chain_tail(s)

    # ---- what the map and the trajectory need ----------------------------------------------------------
    @property
    def anchor(self) -> int:
        """The frame index of the current keyframe (-1 before the first)."""
        return self.keys[-1].index if self.keys else -1

    def take_moves(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """``{keyframe frame index: (pose before, pose now)}`` changed since the last call."""
        moves, self._moves = self._moves, {}
        return moves

    def pose_of(self, index: int, T: np.ndarray) -> np.ndarray:
        """The final corrected pose of frame ``index`` (``T`` when this policy never saw it)."""
        entry = self.frames.get(int(index))
        return T if entry is None else self.corrected[entry[0]] @ entry[1]

    def raw_pose_of(self, index: int, T: np.ndarray) -> np.ndarray:
        """The tracker's own pose of frame ``index`` (``T`` when this policy never saw it)."""
        return self.raw.get(int(index), T)

    def keyframe_pose(self, index: int) -> np.ndarray | None:
        """The corrected pose of the keyframe of frame index ``index`` (None if it is none)."""
        for key, T in zip(self.keys, self.corrected):
            if key.index == index:
                return T
        return None

    def counters(self) -> dict:
        """Loops found (candidates verified), accepted (kept by the graph), rejected, and the time spent."""
        c = self.counts
        return {"policy": self.name, "keyframes": c["keyframes"], "loops_found": c["verified"],
                "loops_accepted": c["accepted"], "loops_rejected": c["rejected_registration"] + c["rejected_graph"],
                "rejected_by_registration": c["rejected_registration"], "rejected_by_graph": c["rejected_graph"],
                "optimisations": c["optimisations"], "refined_edges": c["refined_edges"],
                "skip_edges": c.get("skip_edges", 0), "seconds": self.seconds,
                "worker": "process" if self.background and self.failure is None else "inline",
                "worker_seconds": self.worker_seconds, "worker_cpu_seconds": self.worker_cpu_seconds,
                "keyframe_work": "process" if self.keyframe_worker and self.failure is None else "inline",
                "keyframe_seconds": self.keyframe_seconds, "wait_seconds": self.wait_seconds,
                "worker_held_seconds": self.held_seconds + (self._worker.held_seconds if self._worker else 0.0),
                "worker_failure": self.failure, **self.summary}

    # ---- state -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Plain containers and arrays (:func:`.loop_state.state_of`)."""
        return state_of(self)

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s output, or an older one's (:func:`.loop_state.load_state`)."""
        self.close()  # a worker process holds the keyframes being replaced
        load_state(self, state)
        self._moves, self._submitted, self._rescued = {}, self.settled, None


def _row(r: LoopResult, keys: list[Keyframe]) -> dict:
    return {"frame": keys[r.source].index, "with": keys[r.target].index, "fitness": round(r.fitness, 4),
            "rmse_m": round(r.rmse, 5), "shift_m": round(r.shift, 4), "turn_deg": round(r.turn_deg, 3),
            "accepted": r.accepted, "transform": np.round(r.transform, 6).tolist()}

