"""The keyframes of a :class:`.loop_closure.LoopClosure`: placed by the tracker, built (in the worker process or on
the mapper's thread) and settled into the pose graph, the tail following rigidly.

A new keyframe is placed by the tracker's relative pose from the previous one, with a provisional odometry edge
(that relative pose, unit information). Its build (:func:`.loops.keyframe_data`: cloud, information, refined edge)
runs from its strided depth, kept until it settles. Keyframes settle in order: keyframe ``k``'s edge replaces the
provisional one, its corrected pose becomes ``corrected[k - 1] @ edge``, and the correction that takes it there
moves every later keyframe too: they are placed again by their tracker edges from it, so the relative poses among
them are unchanged, and every move is recorded for the map to follow. Only a settled keyframe looks for loops.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..core.camera import invert_pose
from .loop_worker import LoopWorker, WorkerFailed
from .loops import Keyframe, KeyframeData, candidates, intrinsics, keyframe_data, strided_depth
from .pose_graph import Edge


class KeyframeChain:
    """The keyframe side of :class:`.loop_closure.LoopClosure`, which holds the state it uses (``keys``,
    ``corrected``, ``odo_rel``, ``odo_info``, ``skip_edges``, ``inputs``, ``settled``, ``pending``, the worker and
    counters)."""

    def _add_keyframe(self, index: int, T_raw: np.ndarray, depth, camera) -> None:
        """Place a new keyframe by the tracker's relative pose from the previous one; its build starts (in the
        worker process where one is used) and it settles later (:meth:`_settle_due`)."""
        self.keys.append(Keyframe(int(index), T_raw.copy(), None))
        k = len(self.keys) - 1
        rel = np.eye(4) if k == 0 else invert_pose(self.keys[k - 1].raw_pose) @ T_raw
        self.corrected.append(T_raw.copy() if k == 0 else self.corrected[k - 1] @ rel)
        self.odo_rel.append(rel)
        self.odo_info.append(np.eye(6))
        self.inputs[k] = (strided_depth(depth, self.cfg), intrinsics(camera))
        self.counts["keyframes"] += 1
        self._submit_builds()

    def _submit_builds(self) -> None:
        """Hand the worker the unsettled keyframes it is not building yet (with ``keyframe_worker``)."""
        if not self.keyframe_worker or self.failure is not None:
            return
        try:
            self._submitted = max(self._submitted, self.settled)
            while self._submitted < len(self.keys):
                self._get_worker().build(self.keys, self._submitted, *self.inputs[self._submitted])
                self._submitted += 1
        except WorkerFailed as e:
            self._give_up_worker(str(e))

    def _get_worker(self) -> LoopWorker:
        """The worker process's handle (made on first use): under the real-time clock (``background``: it never
        slows the stream) at the lowest CPU priority on a quarter of the CPUs this process may use, at the mapper's
        priority on all of them otherwise (the mapper waits for its builds)."""
        if self._worker is None:
            usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
            cpus = max(1, usable // 4) if self.background else 0
            self._worker = LoopWorker(self.cfg, nice=19 if self.background else 0, cpus=cpus)
        return self._worker

    def _settle_due(self, index: int | None) -> None:
        """Settle keyframes in order: those ``settle_frames`` before frame ``index`` (waiting for their builds;
        ``index`` None: all of them), and with ``background`` those whose builds have arrived."""
        while self.settled < len(self.keys):
            k = self.settled
            due = index is None or (not self.background and self.keys[k].index + self.cfg.settle_frames <= index)
            if not (due or self.background):
                return
            data = self._built(k, wait=due)
            if data is None:
                return
            self._settle(k, data)

    def _built(self, k: int, wait: bool) -> KeyframeData | None:
        """Keyframe ``k``'s build: from the worker (None while it runs, unless ``wait``), else built here."""
        if self.keyframe_worker and self.failure is None and k < self._submitted:
            t0 = time.perf_counter()
            try:
                data = self._worker.built(k, wait)
                if data is not None:
                    self.keyframe_seconds += data.seconds
                    self.worker_cpu_seconds = self._worker.cpu_seconds
                    return data
                if not wait:
                    return None
            except WorkerFailed as e:
                self._give_up_worker(str(e))
            finally:
                self.wait_seconds += (time.perf_counter() - t0) if wait else 0.0
        data = keyframe_data(self.keys, k, *self.inputs[k], self.cfg)
        self.keyframe_seconds += data.seconds
        return data

    def _settle(self, k: int, data: KeyframeData) -> None:
        """Keyframe ``k``'s cloud, odometry edge and skip edge (if built) enter the graph; its correction moves it
        and the keyframes after it rigidly; its loop candidates replace the waiting ones (not one a failed worker
        held)."""
        key = self.keys[k]
        if key.cloud is None:
            key.cloud = data.cloud()
        new = self.corrected[k] if k == 0 else self.corrected[k - 1] @ data.rel
        self._move_tail(k, new)
        self.odo_rel[k], self.odo_info[k] = np.asarray(data.rel), np.asarray(data.info)
        self.counts["refined_edges"] += int(data.refined)
        if data.skip is not None:
            self.skip_edges.append(Edge(k, k - 2, np.asarray(data.skip[0]), np.asarray(data.skip[1]), False))
            self.counts["skip_edges"] = self.counts.get("skip_edges", 0) + 1
        self.settled = k + 1
        self.inputs.pop(k, None)
        self._drop_old_local_maps(k)
        found = candidates(k, [key.index for key in self.keys], self.corrected, self.cfg)
        self.counts["candidates"] += len(found)
        kept = [p for p in self.pending[:1] if p == self._rescued]
        self.pending = kept + [(k, j) for j in found]  # a newer keyframe's candidates replace an older one's

    def _move_tail(self, k: int, new: np.ndarray) -> None:
        """Keyframe ``k`` to ``new``; the (unsettled) keyframes after it follow by their tracker edges, i.e. by
        the same rigid correction (moves recorded). The tail is chained again from ``new`` rather than multiplied
        by the correction, so rounding does not compound along it."""
        if np.array_equal(self.corrected[k], new):
            return
        self._record_move(k, self.corrected[k], new)
        self._chain_tail(k + 1)

    def _chain_tail(self, start: int) -> None:
        """Keyframes from ``start`` on (unsettled) placed by their provisional edges from the one before."""
        for j in range(start, len(self.keys)):
            self._record_move(j, self.corrected[j], self.corrected[j - 1] @ self.odo_rel[j])

    def _record_move(self, k: int, old: np.ndarray, T: np.ndarray) -> None:
        if not np.allclose(old, T, atol=1e-9):
            first = self._moves.get(self.keys[k].index, (old, T))[0]
            self._moves[self.keys[k].index] = (first, T)
        self.corrected[k] = T

    def _drop_old_local_maps(self, k: int) -> None:
        """Local maps are rebuilt on demand; keep only the recent ones cached (memory stays per keyframe)."""
        old = k - self.cfg.local - 2
        if old >= 0 and self.keys[old].local_cloud is not None:
            self.keys[old].local_cloud = None
