"""Loop closure of a tracked run: keyframes, loop edges and the pose graph, as one policy with explicit state.

The pose source keeps tracking in its own (drifting) frame; this policy keeps, per keyframe, the tracker's pose
and the corrected one. A frame's corrected pose is its tracker pose carried by the correction of its keyframe
(the last keyframe at or before it): ``T = T_corr[k] @ inv(T_raw[k]) @ T_raw``. Every new keyframe looks for loop
candidates (:func:`.loops.candidates`) and verifies at most ``max_candidates`` of them (:func:`.loops.verify`);
an accepted loop edge triggers one optimisation of the graph (:func:`.pose_graph.optimise`), whose line process
may still prune it (then counted as rejected). After an optimisation, :meth:`LoopClosure.take_moves` hands the
caller each keyframe whose corrected pose changed, so the map can follow.

Verification (registration, the expensive part) runs on the mapper's thread, one candidate per frame, or, with
``background``, in a separate process at the lowest CPU priority (:mod:`.loop_worker`: no GIL shared with the
mapper): a frame then only submits the next candidate and takes a finished result, so a real-time stream never
waits for a registration, at the price of results arriving a few frames later (when depends on the machine, so
background verification is for real-time runs; replays on a deterministic clock verify on the mapper's thread).
:meth:`LoopClosure.finish` waits for the last one at the end of the stream and ends the process. Should the
process fail to start, die or fall silent, a ``RuntimeWarning`` says so and verification continues on the mapper's
thread (the candidate it held is verified there at once; nothing already mapped changes).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import invert_pose, rotation_angle_deg
from .loop_worker import LoopWorker, WorkerFailed
from .loops import Keyframe, LoopConfig, LoopResult, candidates, for_source, keyframe_cloud, odometry_edge, verify
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


def loop_closure_for(cfg: LoopClosureConfig, tracked: bool, source=None, realtime: bool = False) -> "LoopClosure | None":
    """The loop-closure policy of a run (None where it is off: poses given, or ``enabled = off``); ``source``:
    the pose source, or its name (``detect.refine_edges = auto`` refines the odometry edges of the
    ``refine_sources``); ``realtime``: the run is on the real-time clock (``background = auto`` verifies in the
    worker process then)."""
    source = getattr(source, "name", source) or ""
    mode, background = str(cfg.enabled).lower(), str(cfg.background).lower()
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"loops.enabled must be auto, on or off, got {cfg.enabled!r}")
    if background not in ("auto", "on", "off"):
        raise ValueError(f"loops.background must be auto, on or off, got {cfg.background!r}")
    if mode == "off" or (mode == "auto" and not tracked):
        return None
    background_on = background == "on" or (background == "auto" and realtime)
    return LoopClosure(for_source(cfg.detect, source), cfg.graph, background=background_on)


class LoopClosure:
    """Keyframes, loop edges and the pose graph of one tracked run.

    ``on_frame(index, T_raw, depth, camera)`` returns the frame's corrected pose; ``anchor`` is the frame index
    of the current keyframe (the anchor of Gaussians created now); ``take_moves()`` returns ``{keyframe index:
    (old pose, new pose)}`` since the last call; ``pose_of(index, T)`` is the final corrected pose of a frame
    that was given pose ``T`` when it was integrated."""

    name = "loop-closure"

    def __init__(self, loops: LoopConfig | None = None, graph: GraphConfig | None = None, *, background: bool = False):
        self.cfg = loops or LoopConfig()
        self.background = bool(background)
        self._job: tuple[int, int] | None = None  # (keyframe, candidate) the worker process is verifying
        self._worker: LoopWorker | None = None  # made on first use
        self.failure: str | None = None  # why the worker process was given up (then verification is inline)
        self.graph_cfg = graph or GraphConfig()
        self.keys: list[Keyframe] = []
        self.corrected: list[np.ndarray] = []  # per keyframe, T_world_cam after the last optimisation
        self.odo_rel: list[np.ndarray] = []  # per keyframe, its odometry edge T_prev_k (the tracker's, or refined)
        self.odo_info: list[np.ndarray] = []  # per keyframe, the information of its edge from the previous one
        self.loop_edges: list[Edge] = []  # accepted by verification (the graph may prune them)
        self.pruned: set[tuple[int, int]] = set()
        self.frames: dict[int, tuple[int, np.ndarray]] = {}  # frame index -> (keyframe position, inv(T_k) @ T)
        self.raw: dict[int, np.ndarray] = {}  # frame index -> the tracker's pose
        self.summary: dict = {}  # ATE before and after, where the run has ground truth (run.poses.loop_closed)
        self.counts = {"keyframes": 0, "candidates": 0, "verified": 0, "rejected_registration": 0,
                       "rejected_graph": 0, "accepted": 0, "optimisations": 0, "refined_edges": 0}
        self.seconds = 0.0  # on the mapper's thread
        self.worker_seconds = 0.0  # verification in the worker process
        self.worker_cpu_seconds = 0.0  # the worker process's CPU time (its own report)
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

    def _is_keyframe(self, index: int, T_raw: np.ndarray) -> bool:
        if not self.keys:
            return True
        last = self.keys[-1]
        delta = invert_pose(last.raw_pose) @ T_raw
        c = self.cfg
        return (np.linalg.norm(delta[:3, 3]) >= c.keyframe_dist or rotation_angle_deg(delta[:3, :3]) >=
                c.keyframe_angle_deg or index - last.index >= c.keyframe_every)

    def _add_keyframe(self, index: int, T_raw: np.ndarray, depth, camera) -> None:
        d = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
        self.keys.append(Keyframe(int(index), T_raw.copy(), keyframe_cloud(d, camera, self.cfg)))
        k = len(self.keys) - 1
        if k == 0:
            self.corrected.append(T_raw.copy())
            self.odo_rel.append(np.eye(4))
            self.odo_info.append(np.eye(6))
        else:  # the odometry edge carries the previous keyframe's correction
            rel, info, refined = odometry_edge(self.keys, k, self.cfg, str(self.cfg.refine_edges).lower() == "on")
            self.corrected.append(self.corrected[k - 1] @ rel)
            self.odo_rel.append(rel)
            self.odo_info.append(info)
            self.counts["refined_edges"] += int(refined)
        self.counts["keyframes"] += 1
        self._drop_old_local_maps(k)
        indices = [key.index for key in self.keys]
        found = candidates(k, indices, self.corrected, self.cfg)
        self.counts["candidates"] += len(found)
        self.pending = [(k, j) for j in found]  # a newer keyframe's candidates replace an older one's

    def _drop_old_local_maps(self, k: int) -> None:
        """Local maps are rebuilt on demand; keep only the recent ones cached (memory stays per keyframe)."""
        old = k - self.cfg.local - 2
        if old >= 0 and self.keys[old].local_cloud is not None:
            self.keys[old].local_cloud = None

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
                if self._worker is None:
                    self._worker = LoopWorker(self.cfg)
                self._job = self.pending.pop(0)
                self._worker.submit(self.keys, self.corrected, *self._job)
        except WorkerFailed as e:
            self._give_up_worker(str(e))
        return found

    def _give_up_worker(self, why: str) -> None:
        """Verify on the mapper's thread from now on; the candidate the worker held waits first in line."""
        self.failure = f"{why}; loop candidates are verified on the mapper's thread from now on"
        warnings.warn(self.failure, RuntimeWarning, stacklevel=2)
        self.close(kill=True)

    def finish(self) -> None:
        """At the end of the stream: wait for a verification still in the worker (verified here should the worker
        fail) and, if it closed a loop, optimise (:meth:`take_moves` then has the moves); the worker ends."""
        t0 = time.perf_counter()
        try:
            found = False
            if self._job is not None:
                running = self._job
                found = self._verify_in_background(wait=True)
                if self.failure is not None and self.pending[:1] == [running]:
                    found |= self._take(verify(self.keys, self.corrected, *self.pending.pop(0), self.cfg))
            if found:
                self._optimise()
        finally:
            self.seconds += time.perf_counter() - t0
            self.close()

    def close(self, kill: bool = False) -> None:
        """End the worker process, if one runs (``kill``: without waiting for it); the candidate it held goes back
        to the front of the queue."""
        if self._job is not None:
            self.pending.insert(0, self._job)
            self._job = None
        if self._worker is not None:
            self.worker_cpu_seconds = max(self.worker_cpu_seconds, self._worker.cpu_seconds)
            self._worker.close(kill)
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
        edges = odometry_edges(self.odo_rel, self.odo_info) + self.loop_edges
        new, kept = optimise(self.corrected, edges, self.graph_cfg)
        self.counts["optimisations"] += 1
        self.pruned = {(e.source, e.target) for e, ok in zip(self.loop_edges, kept) if not ok}
        self.counts["accepted"] = sum(kept)
        self.counts["rejected_graph"] = len(self.pruned)
        for k, (old, T) in enumerate(zip(self.corrected, new)):
            if not np.allclose(old, T, atol=1e-9):
                first = self._moves.get(self.keys[k].index, (old, T))[0]
                self._moves[self.keys[k].index] = (first, T)
        self.corrected = new

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
                "optimisations": c["optimisations"], "refined_edges": c["refined_edges"], "seconds": self.seconds,
                "worker": "process" if self.background and self.failure is None else "inline",
                "worker_seconds": self.worker_seconds, "worker_cpu_seconds": self.worker_cpu_seconds,
                "worker_failure": self.failure, **self.summary}

    # ---- state -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Plain containers and arrays: keyframes (index, tracker pose, cloud points and normals), corrected
        poses, edges, frames' offsets, counters."""
        keys = [{"index": k.index, "raw_pose": k.raw_pose, "points": np.asarray(k.cloud.points).copy(),
                 "normals": np.asarray(k.cloud.normals).copy()} for k in self.keys]
        edges = [{"source": e.source, "target": e.target, "transform": e.transform, "information": e.information}
                 for e in self.loop_edges]
        return {"keys": keys, "corrected": [T.copy() for T in self.corrected], "odo_rel": list(self.odo_rel),
                "odo_info": list(self.odo_info),
                "loop_edges": edges, "pruned": sorted(self.pruned),
                "pending": [list(p) for p in ([self._job] if self._job else []) + self.pending],  # running first
                "counts": dict(self.counts),
                "seconds": self.seconds, "frames": {int(i): [k, rel.copy()] for i, (k, rel) in self.frames.items()},
                "raw": {int(i): T.copy() for i, T in self.raw.items()}, "log": list(self.log)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s output."""
        import open3d as o3d

        self.close()  # a worker process holds the keyframes being replaced
        self.keys = []
        for k in state["keys"]:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(k["points"], dtype=np.float64)))
            pcd.normals = o3d.utility.Vector3dVector(np.asarray(k["normals"], dtype=np.float64))
            self.keys.append(Keyframe(int(k["index"]), np.asarray(k["raw_pose"], dtype=np.float64), pcd))
        self.corrected = [np.asarray(T, dtype=np.float64) for T in state["corrected"]]
        self.odo_info = [np.asarray(x, dtype=np.float64) for x in state["odo_info"]]
        raw = [key.raw_pose for key in self.keys]  # a checkpoint without refined edges: the tracker's
        self.odo_rel = [np.asarray(x, dtype=np.float64) for x in state.get("odo_rel", [])] or (
            [np.eye(4)] + [invert_pose(a) @ b for a, b in zip(raw, raw[1:])])
        self.loop_edges = [Edge(int(e["source"]), int(e["target"]), np.asarray(e["transform"], dtype=np.float64),
                                np.asarray(e["information"], dtype=np.float64), True) for e in state["loop_edges"]]
        self.pruned = {tuple(p) for p in state["pruned"]}
        self.pending = [(int(k), int(j)) for k, j in state.get("pending", [])]
        self.counts.update(state["counts"])
        self.seconds = float(state["seconds"])
        self.frames = {int(i): (int(v[0]), np.asarray(v[1], dtype=np.float64)) for i, v in state["frames"].items()}
        self.raw = {int(i): np.asarray(T, dtype=np.float64) for i, T in state["raw"].items()}
        self.log = list(state.get("log", []))
        self._moves = {}


def _row(r: LoopResult, keys: list[Keyframe]) -> dict:
    return {"frame": keys[r.source].index, "with": keys[r.target].index, "fitness": round(r.fitness, 4),
            "rmse_m": round(r.rmse, 5), "shift_m": round(r.shift, 4), "turn_deg": round(r.turn_deg, 3),
            "accepted": r.accepted, "transform": np.round(r.transform, 6).tolist()}

