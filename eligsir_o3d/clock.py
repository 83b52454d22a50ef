"""Clocks that release a recorded stream to the Reconstructor.

- :class:`RealtimeClock`: frames are released at their timestamps (divided by ``speed``) against the wall clock;
  the mapper gets only the time that really passes, tracking and frame decoding included. Released frames wait
  in a bounded queue; when it is full the **oldest waiting frame is dropped** (a robot cares most about the newest
  view, and the backlog, hence the lag, stays bounded). Dropped frames are counted in :class:`ClockReport`.
- :class:`BudgetClock` (deterministic): the same replay against *modelled* time - a :class:`CostModel` of
  seconds per update (supervised pixels, Gaussians) and per frame stands in for the wall clock, so backlog, drops
  and the fidelity controller's decisions are reproducible on any machine (tests, ablations). With
  ``updates_per_frame`` it instead grants a fixed number of updates to every frame (no backlog).

Both set ``rec.backlog`` (frames waiting) for Load-Adaptive Fidelity, hand it the frame period (and, for the
budget clock, the cost model), and either skip a frame that raises :class:`FrameError` (recording
``"frame i: reason"`` in ``report.skipped_bad``) or re-raise it (``on_bad_frame="stop"``).

Items of ``frames`` are :class:`Frame` objects (pose and timestamp inside) or ``(rgbd, pose, timestamp)`` tuples
(``pose=None`` lets the Reconstructor's pose source track the frame, inside the mapper's time).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .frame import Frame, FrameError


@dataclass
class ClockReport:
    released: int = 0
    integrated: int = 0
    dropped: int = 0
    dropped_indices: list[int] = field(default_factory=list)
    skipped_bad: list[str] = field(default_factory=list)
    max_backlog: int = 0  # most frames ever waiting in the queue
    stream_s: float = 0.0  # duration of the replayed stream (last minus first timestamp, divided by speed)
    elapsed_s: float = 0.0  # mapper time from the first release to the end of the last frame (wall or modelled)


@dataclass
class CostModel:
    """Modelled seconds of the mapper's work. One update of ``pixels`` supervised pixels on a map of ``gaussians``:
    ``update_s + gaussian_s * gaussians + pixels * (pixel_s + pixel_gaussian_s * gaussians)`` (projection and Adam
    grow with N; blending grows with pixels times the Gaussians overlapping each pixel). One integrated frame
    (admission render, growth): ``frame_s + gaussian_s * gaussians``.

    Defaults: ``python benchmarks/cost_model.py --frames 300`` on the project's reference machine (2 cores, the
    ``cpu`` renderer on 2 threads, the default policies mapping the first 300 frames of 7-Scenes redkitchen,
    1k-8k Gaussians): an 80x60 update ~12 ms, 160x120 ~19 ms, 320x240 ~45 ms, 640x480 ~0.13 s; median
    predicted/measured 0.97. Run that script to fit another machine and pass its output with ``--config``.
    """

    update_s: float = 0.0059
    gaussian_s: float = 1.1e-6
    pixel_s: float = 2.0e-7
    pixel_gaussian_s: float = 5.9e-11
    frame_s: float = 0.0024

    @classmethod
    def fit(cls, updates: np.ndarray, frames: np.ndarray) -> "CostModel":
        """Fit to timings: ``updates`` rows ``(pixels, gaussians, seconds)``, ``frames`` rows ``(gaussians, seconds)``.

        Non-negative least squares on relative error (every update weighs the same whatever its size); the frame
        term shares ``gaussian_s`` and takes the mean remainder (the budget is a sum over frames).
        """
        u = np.asarray(updates, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(frames, dtype=np.float64).reshape(-1, 2)
        if len(u) < 4 or not np.all(u[:, 2] > 0):
            raise ValueError(f"need at least 4 update timings, all positive; got {len(u)}")
        P, G, t = u[:, 0], u[:, 1], u[:, 2]
        A = np.stack([np.ones_like(P), G, P, P * G], 1) / t[:, None]
        norm = np.maximum(np.linalg.norm(A, axis=0), 1e-300)  # columns span 10 orders of magnitude
        a = _nnls(A / norm, np.ones_like(t)) / norm
        frame_s = float(np.mean(np.maximum(f[:, 1] - a[1] * f[:, 0], 0.0))) if len(f) else cls.frame_s
        return cls(update_s=float(a[0]), gaussian_s=float(a[1]), pixel_s=float(a[2]), pixel_gaussian_s=float(a[3]),
                   frame_s=frame_s)

    def update(self, pixels: int, gaussians: int) -> float:
        return self.update_s + self.gaussian_s * gaussians + pixels * (self.pixel_s + self.pixel_gaussian_s * gaussians)

    def frame(self, gaussians: int) -> float:
        return self.frame_s + self.gaussian_s * gaussians


def _nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Non-negative least squares for a handful of unknowns: the best unconstrained solution over every subset of
    free variables that comes out non-negative (exact, 2^n small solves)."""
    n = A.shape[1]
    best, best_r = np.zeros(n), float(np.sum(b * b))
    for k in range(1, n + 1):
        for free in combinations(range(n), k):
            x_free = np.linalg.lstsq(A[:, free], b, rcond=None)[0]
            if np.any(x_free < 0):
                continue
            x = np.zeros(n)
            x[list(free)] = x_free
            r = float(np.sum((A @ x - b) ** 2))
            if r < best_r:
                best, best_r = x, r
    return best


@dataclass
class ClockConfig:
    mode: str = "budget"  # budget (deterministic, modelled time) | realtime (wall clock)
    budget: str = "cost"  # budget mode: cost (replay against the cost model) | updates (optim.updates_per_frame each)
    speed: float = 1.0  # replay speed: 0.25 releases frames at a quarter of the recorded rate
    queue_size: int = 4  # frames that may wait for the mapper; beyond it the oldest waiting frame is dropped
    min_updates_behind: int = 1  # updates granted to a frame integrated while others wait (the map keeps learning)
    on_bad_frame: str = "skip"  # skip | stop
    cost: CostModel = field(default_factory=CostModel)


def _check_bad(on_bad_frame: str) -> str:
    if on_bad_frame not in ("skip", "stop"):
        raise ValueError(f"on_bad_frame must be 'skip' or 'stop', got {on_bad_frame!r}")
    return on_bad_frame


def _stamp(item: Any, k: int) -> float:
    if isinstance(item, Frame):
        return float(item.timestamp)
    if isinstance(item, (tuple, list)) and len(item) >= 3 and item[2] is not None:
        return float(item[2])
    return k / 30.0


def _index(item: Any, k: int) -> int:
    return int(item.index) if isinstance(item, Frame) else k


class _Replay(ABC):
    """Release frames by timestamp against a time source; a bounded drop-oldest queue; backlog to the mapper."""

    name = "replay"

    def __init__(self, speed: float = 1.0, queue_size: int = 4, min_updates_behind: int = 1,
                 on_bad_frame: str = "skip"):
        if not speed > 0:
            raise ValueError(f"speed must be positive, got {speed}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.speed = float(speed)
        self.queue_size = int(queue_size)
        self.min_updates_behind = int(min_updates_behind)
        self.on_bad_frame = _check_bad(on_bad_frame)

    # time source hooks
    @abstractmethod
    def now(self, rec) -> float:
        raise NotImplementedError

    @abstractmethod
    def attach(self, rec, period_s: float) -> None:
        raise NotImplementedError

    @abstractmethod
    def work(self, rec, item, deadline: float | None, behind: bool) -> None:
        """Integrate ``item`` and optimise: ``min_updates_behind`` updates if behind, else until ``deadline``."""
        raise NotImplementedError

    @abstractmethod
    def idle(self, rec, deadline: float) -> None:
        """Nothing waits: optimise (or wait) until ``deadline``."""
        raise NotImplementedError

    def run(self, rec, frames: Iterable, on_release: Callable[[Any], None] | None = None) -> ClockReport:
        report = ClockReport()
        it = iter(frames)
        k = 0
        pending, k = self._next(it, k, report)
        if pending is None:
            return report
        t_first = _stamp(pending, k - 1)
        start = self.now(rec)
        release = lambda item, j: start + (_stamp(item, j) - t_first) / self.speed  # noqa: E731
        queue: deque = deque()
        period = 1.0 / 30.0 / self.speed
        last_stamp = t_first
        while pending is not None or queue:
            now = self.now(rec)
            while pending is not None and release(pending, k - 1) <= now:
                report.released += 1
                stamp = _stamp(pending, k - 1)
                if stamp > last_stamp:
                    # the mean frame period so far: gaps (held-out frames, hiccups) must not look like spare time
                    period = (stamp - t_first) / max(1, report.released - 1) / self.speed
                    last_stamp = stamp
                if on_release is not None:
                    on_release(pending)
                if len(queue) >= self.queue_size:
                    old, j = queue.popleft()
                    report.dropped += 1
                    report.dropped_indices.append(_index(old, j))
                queue.append((pending, k - 1))
                pending, k = self._next(it, k, report)
            report.max_backlog = max(report.max_backlog, len(queue))
            self.attach(rec, period)
            next_release = release(pending, k - 1) if pending is not None else None
            if not queue:
                rec.backlog = 0
                self.idle(rec, next_release)
                continue
            item, j = queue.popleft()
            rec.backlog = len(queue)
            behind = bool(queue) or (next_release is not None and next_release <= self.now(rec))
            deadline = next_release if next_release is not None else self.now(rec) + period
            try:
                self.work(rec, item, deadline, behind)
                report.integrated += 1
            except FrameError as e:
                if self.on_bad_frame == "stop":
                    raise
                report.skipped_bad.append(_bad(item, j, e))
        rec.backlog = 0
        report.stream_s = (last_stamp - t_first) / self.speed
        report.elapsed_s = self.now(rec) - start
        return report

    def _next(self, it: Iterator, k: int, report: ClockReport):
        """The next item of the stream (None at its end); a FrameError raised while reading it is skipped."""
        while True:
            try:
                return next(it), k + 1
            except StopIteration:
                return None, k
            except FrameError as e:
                if self.on_bad_frame == "stop":
                    raise
                report.skipped_bad.append(str(e) if str(e).startswith("frame ") else f"frame {k}: {e}")
                k += 1


def _bad(item, j: int, e: Exception) -> str:
    msg = str(e)
    return msg if msg.startswith("frame ") else f"frame {_index(item, j)}: {msg}"


def _integrate(rec, item, **kw):
    if isinstance(item, Frame):
        return rec.integrate(item, **kw)
    rgbd, pose, stamp = (tuple(item) + (None, None))[:3]
    return rec.integrate(rgbd, pose, stamp, **kw)


class RealtimeClock(_Replay):
    """Real-time replay against the wall clock (``rec.clock_now()``, which excludes evaluation callbacks)."""

    name = "realtime"

    def __init__(self, speed: float = 1.0, queue_size: int = 4, min_updates_behind: int = 1,
                 on_bad_frame: str = "skip", sleep: Callable[[float], None] = time.sleep):
        super().__init__(speed, queue_size, min_updates_behind, on_bad_frame)
        self._sleep = sleep

    def now(self, rec) -> float:
        return rec.clock_now()

    def attach(self, rec, period_s: float) -> None:
        attach = getattr(rec.fidelity, "attach", None)
        if attach is not None:
            attach(period_s, None)

    def work(self, rec, item, deadline, behind: bool) -> None:
        if behind:
            _integrate(rec, item, updates=self.min_updates_behind)
        else:
            _integrate(rec, item, deadline=deadline)

    def idle(self, rec, deadline: float) -> None:
        if rec.optimize(deadline=deadline) == 0:
            wait = deadline - self.now(rec)
            if wait > 0:
                self._sleep(wait)


class BudgetClock(_Replay):
    """Deterministic budget. With ``updates_per_frame``: that many updates per released frame, every frame
    integrated. Without: replay against modelled time (``cost``), with backlog and drops as in real time."""

    name = "budget"

    def __init__(self, updates_per_frame: int | None = None, cost: CostModel | None = None, speed: float = 1.0,
                 queue_size: int = 4, min_updates_behind: int = 1, on_bad_frame: str = "skip"):
        super().__init__(speed, queue_size, min_updates_behind, on_bad_frame)
        self.updates_per_frame = None if updates_per_frame is None else int(updates_per_frame)
        self.cost = cost or CostModel()
        self.t = 0.0  # modelled seconds

    def run(self, rec, frames: Iterable, on_release: Callable[[Any], None] | None = None) -> ClockReport:
        self.t = 0.0
        if self.updates_per_frame is None:
            return super().run(rec, frames, on_release)
        report = ClockReport()
        it, k = iter(frames), 0
        stamps = []
        while True:
            item, k = self._next(it, k, report)
            if item is None:
                break
            report.released += 1
            stamps.append(_stamp(item, k - 1))
            if len(stamps) > 1 and stamps[-1] > stamps[0]:
                self.attach(rec, (stamps[-1] - stamps[0]) / (len(stamps) - 1) / self.speed)
            if on_release is not None:
                on_release(item)
            try:
                _integrate(rec, item, updates=0)
                self.t += self.cost.frame(len(rec.gmap))
                self._updates(rec, self.updates_per_frame)
                report.integrated += 1
            except FrameError as e:
                if self.on_bad_frame == "stop":
                    raise
                report.skipped_bad.append(_bad(item, k - 1, e))
        report.stream_s = (stamps[-1] - stamps[0]) / self.speed if stamps else 0.0
        report.elapsed_s = self.t
        return report

    def now(self, rec) -> float:
        return self.t

    def attach(self, rec, period_s: float) -> None:
        attach = getattr(rec.fidelity, "attach", None)
        if attach is not None:
            attach(period_s, lambda pixels: self.cost.update(pixels, len(rec.gmap)))

    def _updates(self, rec, n: int | None, deadline: float | None = None) -> int:
        """One update at a time, each advancing modelled time; stops at ``n`` updates or at ``deadline``."""
        done = 0
        while (n is None or done < n) and (deadline is None or self.t < deadline):
            px = rec.stats.supervised_pixels
            if rec.optimize(1) == 0:
                break
            self.t += self.cost.update(rec.stats.supervised_pixels - px, len(rec.gmap))
            done += 1
        return done

    def work(self, rec, item, deadline, behind: bool) -> None:
        _integrate(rec, item, updates=0)
        self.t += self.cost.frame(len(rec.gmap))
        if behind:
            self._updates(rec, self.min_updates_behind)
        else:
            self._updates(rec, None, deadline)

    def idle(self, rec, deadline: float) -> None:
        self._updates(rec, None, deadline)
        self.t = max(self.t, deadline)


def get_clock(cfg) -> _Replay:
    """The clock a :class:`Config` asks for (``cfg.clock``; the fixed-updates budget uses ``cfg.optim``)."""
    c = cfg.clock
    common = dict(speed=c.speed, queue_size=c.queue_size, min_updates_behind=c.min_updates_behind,
                  on_bad_frame=c.on_bad_frame)
    if c.mode == "realtime":
        return RealtimeClock(**common)
    if c.mode != "budget":
        raise ValueError(f"clock mode must be 'budget' or 'realtime', got {c.mode!r}")
    if c.budget == "updates":
        return BudgetClock(cfg.optim.updates_per_frame, c.cost, **common)
    if c.budget != "cost":
        raise ValueError(f"clock budget must be 'cost' or 'updates', got {c.budget!r}")
    return BudgetClock(None, c.cost, **common)
