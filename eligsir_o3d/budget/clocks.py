"""Clocks that release a recorded stream to the Reconstructor.

- :class:`RealtimeClock`: frames are released at their timestamps (divided by ``speed``) against the wall clock;
  the mapper gets only the time that really passes, tracking and frame decoding included. Released frames wait
  in a bounded queue; when it is full the **oldest waiting frame is dropped** (a robot cares most about the newest
  view, and the backlog, hence the lag, stays bounded). Dropped frames are counted in :class:`ClockReport`.
- :class:`BudgetClock` (deterministic): the same replay against *modelled* time - a :class:`CostModel` of
  seconds per update (supervised pixels, Gaussians) and per frame stands in for the wall clock, so backlog, drops
  and the fidelity controller's decisions are reproducible on any machine (tests, ablations). With
  ``updates_per_frame`` it instead grants a fixed number of updates to every frame (no backlog).

Load reaches the mapper through one verb, ``rec.set_load(backlog, period_s, cost)`` (frames waiting, the time one
frame grants, and for the cost clock the model that prices an update). A frame that raises :class:`FrameError` is
skipped (recorded as ``"frame i: reason"`` in ``report.skipped_bad``) or re-raised (``on_bad_frame="stop"``).
After the stream, :meth:`drain` runs the bounded drain that the clock allows.

Items of ``frames`` are :class:`Frame` objects (pose and timestamp inside) or ``(rgbd, pose, timestamp)`` tuples
(``pose=None`` lets the Reconstructor's pose source track the frame, inside the mapper's time).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator

import torch

from ..core.frame import Frame, FrameError
from .clock import DEFAULT_FRAME_PERIOD_S
from .cost import CostModel, priced_gaussians


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
    cost_factor: float = 1.0  # cost clock with feedback: measured / modelled seconds of the work, at the end
    drain_s: float = 0.0  # cost clock: modelled seconds of the bounded drain after the stream (not in elapsed_s)


def _check_bad(on_bad_frame: str) -> str:
    if on_bad_frame not in ("skip", "stop"):
        raise ValueError(f"on_bad_frame must be 'skip' or 'stop', got {on_bad_frame!r}")
    return on_bad_frame


def _stamp(item: Any, k: int, period_s: float) -> float:
    if isinstance(item, Frame):
        return float(item.timestamp)
    if isinstance(item, (tuple, list)) and len(item) >= 3 and item[2] is not None:
        return float(item[2])
    return k * period_s


def _index(item: Any, k: int) -> int:
    return int(item.index) if isinstance(item, Frame) else k


class _Replay(ABC):
    """Release frames by timestamp against a time source; a bounded drop-oldest queue; load to the mapper."""

    name = "replay"
    factor = 1.0  # measured / modelled seconds of the work (the cost clock's feedback; 1 for the others)

    def __init__(self, speed: float = 1.0, queue_size: int = 4, min_updates_behind: int = 1,
                 on_bad_frame: str = "skip", frame_period_s: float = DEFAULT_FRAME_PERIOD_S):
        if not speed > 0:
            raise ValueError(f"speed must be positive, got {speed}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.speed = float(speed)
        self.queue_size = int(queue_size)
        self.min_updates_behind = int(min_updates_behind)
        self.on_bad_frame = _check_bad(on_bad_frame)
        self.frame_period_s = float(frame_period_s)

    # time source hooks
    @abstractmethod
    def now(self, rec) -> float:
        raise NotImplementedError

    @abstractmethod
    def load(self, rec, backlog: int, period_s: float | None) -> None:
        """Tell the mapper its load (``rec.set_load``), with this clock's way of pricing an update."""
        raise NotImplementedError

    @abstractmethod
    def work(self, rec, item, deadline: float | None, behind: bool) -> None:
        """Integrate ``item`` and optimise: ``min_updates_behind`` updates if behind, else until ``deadline``."""
        raise NotImplementedError

    @abstractmethod
    def idle(self, rec, deadline: float) -> None:
        """Nothing waits: optimise (or wait) until ``deadline``."""
        raise NotImplementedError

    @abstractmethod
    def drain(self, rec, acquisition_s: float) -> None:
        """The bounded drain after the stream (``rec.finalize``), bounded as this clock allows."""
        raise NotImplementedError

    def _stamp(self, item, k: int) -> float:
        return _stamp(item, k, self.frame_period_s)

    def run(self, rec, frames: Iterable, on_release: Callable[[Any], None] | None = None) -> ClockReport:
        report = ClockReport()
        it = iter(frames)
        k = 0
        pending, k = self._next(it, k, report)
        if pending is None:
            return report
        t_first = self._stamp(pending, k - 1)
        start = self.now(rec)
        release = lambda item, j: start + (self._stamp(item, j) - t_first) / self.speed  # noqa: E731
        queue: deque = deque()
        period = self.frame_period_s / self.speed
        last_stamp = t_first
        while pending is not None or queue:
            now = self.now(rec)
            while pending is not None and release(pending, k - 1) <= now:
                report.released += 1
                stamp = self._stamp(pending, k - 1)
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
            next_release = release(pending, k - 1) if pending is not None else None
            if not queue:
                self.load(rec, 0, period)
                self.idle(rec, next_release)
                continue
            item, j = queue.popleft()
            self.load(rec, len(queue), period)
            behind = bool(queue) or (next_release is not None and next_release <= self.now(rec))
            deadline = next_release if next_release is not None else self.now(rec) + period
            try:
                self.work(rec, item, deadline, behind)
                report.integrated += 1
            except FrameError as e:
                if self.on_bad_frame == "stop":
                    raise
                report.skipped_bad.append(_bad(item, j, e))
        rec.set_load(0)
        report.stream_s = (last_stamp - t_first) / self.speed
        report.elapsed_s = self.now(rec) - start
        report.cost_factor = float(self.factor)
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


def _updates_behind(rec, n: int) -> int:
    """Updates for the frame just integrated while others wait: ``n``, or none when the load policy shed them."""
    plan = getattr(rec, "frame_plan", None)
    return n if plan is None or plan.update_behind else 0


def _integrate(rec, item, **kw):
    if isinstance(item, Frame):
        return rec.integrate(item, **kw)
    rgbd, pose, stamp = (tuple(item) + (None, None))[:3]
    return rec.integrate(rgbd, pose, stamp, **kw)


class RealtimeClock(_Replay):
    """Real-time replay against the wall clock (``rec.clock_now()``, which excludes evaluation callbacks)."""

    name = "realtime"

    def __init__(self, speed: float = 1.0, queue_size: int = 4, min_updates_behind: int = 1,
                 on_bad_frame: str = "skip", sleep: Callable[[float], None] = time.sleep,
                 frame_period_s: float = DEFAULT_FRAME_PERIOD_S, drain_fraction: float = 0.03):
        super().__init__(speed, queue_size, min_updates_behind, on_bad_frame, frame_period_s)
        self._sleep = sleep
        self.drain_fraction = float(drain_fraction)

    def now(self, rec) -> float:
        return rec.clock_now()

    def load(self, rec, backlog: int, period_s: float | None) -> None:
        rec.set_load(backlog, period_s)

    def work(self, rec, item, deadline, behind: bool) -> None:
        if behind:
            _integrate(rec, item, updates=0)
            rec.optimize(_updates_behind(rec, self.min_updates_behind))
        else:
            _integrate(rec, item, deadline=deadline)

    def idle(self, rec, deadline: float) -> None:
        if rec.optimize(deadline=deadline) == 0:
            wait = deadline - self.now(rec)
            if wait > 0:
                self._sleep(wait)

    def drain(self, rec, acquisition_s: float) -> None:
        # bounded in time too, so that the ME map is ready about when the stream ends
        rec.finalize(rec.clock_now() + self.drain_fraction * acquisition_s)


class BudgetClock(_Replay):
    """Deterministic budget. With ``updates_per_frame``: that many updates per released frame, every frame
    integrated. Without: replay against modelled time (``cost``), with backlog and drops as in real time."""

    def __init__(self, updates_per_frame: int | None = None, cost: CostModel | None = None, speed: float = 1.0,
                 queue_size: int = 4, min_updates_behind: int = 1, on_bad_frame: str = "skip",
                 frame_period_s: float = DEFAULT_FRAME_PERIOD_S, feedback: float = 0.0,
                 drain_updates: int | None = None):
        super().__init__(speed, queue_size, min_updates_behind, on_bad_frame, frame_period_s)
        self.updates_per_frame = None if updates_per_frame is None else int(updates_per_frame)
        self.cost = cost or CostModel()
        self.t = 0.0  # modelled seconds
        # clock.cost_feedback: an EMA of measured / modelled seconds scales what is charged (0: factor stays 1.0)
        self.feedback = float(feedback)
        self.factor = 1.0
        self.drain_updates = None if drain_updates is None else int(drain_updates)  # None: rec.finalize, unpriced

    def _measured(self, rec, t0: float) -> float:
        """Wall seconds since ``t0``; with feedback on CUDA, once the device has finished the (asynchronous) work."""
        if self.feedback > 0:
            device = getattr(rec, "device", None)
            if device is not None and torch.device(device).type == "cuda":
                torch.cuda.synchronize(device)
        return time.perf_counter() - t0

    def _priced(self, modelled: float, measured: float) -> float:
        """Modelled seconds of one piece of work, corrected; with feedback, ``measured`` updates the correction."""
        if self.feedback > 0 and modelled > 0:
            ratio = min(max(measured / modelled, 0.25), 4.0)  # one stall (a page fault, a compile) is not a trend
            self.factor += self.feedback * (ratio - self.factor)
        return modelled * self.factor

    @property
    def name(self) -> str:
        """The clock mode: ``cost`` (modelled time) or ``updates`` (a fixed number per frame)."""
        return "cost" if self.updates_per_frame is None else "updates"

    def run(self, rec, frames: Iterable, on_release: Callable[[Any], None] | None = None) -> ClockReport:
        self.t = 0.0
        if self.updates_per_frame is None:
            return super().run(rec, frames, on_release)
        report = ClockReport()
        it, k = iter(frames), 0
        stamps = []
        period = self.frame_period_s / self.speed  # until two stamps give the recording's own
        while True:
            item, k = self._next(it, k, report)
            if item is None:
                break
            report.released += 1
            stamps.append(self._stamp(item, k - 1))
            if len(stamps) > 1 and stamps[-1] > stamps[0]:
                period = (stamps[-1] - stamps[0]) / (len(stamps) - 1) / self.speed
            # from the first frame on: the fidelity policy prices updates with the cost model, never with measured
            # seconds, so the run does not depend on the machine's speed or load
            self.load(rec, 0, period)
            if on_release is not None:
                on_release(item)
            try:
                _integrate(rec, item, updates=0)
                self.t += self.cost.frame(priced_gaussians(rec))
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

    def load(self, rec, backlog: int, period_s: float | None) -> None:
        rec.set_load(backlog, period_s, self.cost if self.factor == 1.0 else self.cost.scaled(self.factor))

    def _updates(self, rec, n: int | None, deadline: float | None = None) -> int:
        """One update at a time, each advancing modelled time; stops at ``n`` updates or at ``deadline``."""
        done = 0
        while (n is None or done < n) and (deadline is None or self.t < deadline):
            px = rec.stats.supervised_pixels
            t0 = time.perf_counter()
            if rec.optimize(1) == 0:
                break
            dt = self._measured(rec, t0)
            self.t += self._priced(self.cost.update(rec.stats.supervised_pixels - px, priced_gaussians(rec)), dt)
            done += 1
        return done

    def work(self, rec, item, deadline, behind: bool) -> None:
        t0 = time.perf_counter()
        _integrate(rec, item, updates=0)
        dt = self._measured(rec, t0)
        # a frame without the full admission check (scheduling.load) pays no support render: no Gaussian term
        plan = getattr(rec, "frame_plan", None)
        self.t += self._priced(self.cost.frame(priced_gaussians(rec)) if plan is None or plan.check
                               else self.cost.frame_s, dt)
        if behind:
            self._updates(rec, _updates_behind(rec, self.min_updates_behind))
        else:
            self._updates(rec, None, deadline)

    def idle(self, rec, deadline: float) -> None:
        self._updates(rec, None, deadline)
        self.t = max(self.t, deadline)

    def drain(self, rec, acquisition_s: float) -> float:
        """The bounded drain (as ``rec.finalize``), priced like any update; returns its modelled seconds."""
        if self.drain_updates is None:
            rec.finalize()
            return 0.0
        t0 = self.t
        with rec.views.drain():
            self._updates(rec, self.drain_updates)
        return self.t - t0
