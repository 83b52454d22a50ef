"""Where the mapper's time goes: wall seconds and calls per named stage.

The Reconstructor times its own stages with one :class:`StageTimes` (``rec.timing``): ``admission`` and
``growth`` (the per-frame fixed work of every integrated frame), ``update`` (optimisation updates) and ``tracking``
(a pose source); the pipeline adds ``decode`` (reading the recording, off the mapper's clock). metrics.json holds
:meth:`StageTimes.summary` as ``stage_times``. Two ``perf_counter`` calls per stage, nothing else.

:func:`detail` adds sub-stages (the support render, the voxel hash, view bookkeeping, scheduling, MCMC) by
wrapping bound methods of one Reconstructor's policies, so the policies carry no timing code; benchmarks use it
(``benchmarks/budget/realtime_load.py --breakdown``). Nested stages are reported as they are: a sub-stage's seconds are
also in its parent's.
"""

from __future__ import annotations

import functools
import time
from contextlib import contextmanager


class StageTimes:
    """Accumulated wall seconds and calls per stage name."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    @contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def add(self, name: str, seconds: float, calls: int = 1) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)
        self.calls[name] = self.calls.get(name, 0) + int(calls)

    def total(self, *names: str) -> float:
        return sum(self.seconds.get(n, 0.0) for n in names)

    def summary(self, frames: int | None = None) -> dict:
        """``{stage: {"s", "calls", "ms_per_call"[, "ms_per_frame"]}}``; ``frames``: integrated frames, for the
        per-frame share of each stage."""
        out = {}
        for name, s in sorted(self.seconds.items(), key=lambda kv: -kv[1]):
            n = self.calls.get(name, 0)
            row = {"s": round(s, 4), "calls": n, "ms_per_call": round(1e3 * s / n, 3) if n else None}
            if frames:
                row["ms_per_frame"] = round(1e3 * s / frames, 3)
            out[name] = row
        return out

    def state_dict(self) -> dict:
        return {"seconds": dict(self.seconds), "calls": dict(self.calls)}

    def load_state_dict(self, state: dict) -> None:
        self.seconds, self.calls = dict(state.get("seconds", {})), dict(state.get("calls", {}))


def _wrap(timing: StageTimes, obj, attr: str, name: str) -> None:
    fn = getattr(obj, attr, None)
    if fn is None or getattr(fn, "_stage", None) == name:
        return

    @functools.wraps(fn)
    def timed(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            timing.add(name, time.perf_counter() - t0)

    timed._stage = name
    setattr(obj, attr, timed)


# (path from the Reconstructor, method, stage name): what the per-frame and per-update fixed work is made of
DETAIL = (
    ("views", "is_redundant", "admission.pose_filter"),
    ("views.probe", "check", "support_render"),  # shared by admission and growth (cached per frame)
    ("views", "_admit", "admission.view_bookkeeping"),  # footprint cells, coverage, priority refresh
    ("views", "refresh", "scheduling.refresh"),
    ("views", "select", "scheduling.select"),
    ("views", "feedback", "scheduling.feedback"),
    ("growth.voxels", "lookup", "growth.voxel_hash"),
    ("growth", "_insert", "growth.insert"),
    ("growth", "post_step", "update.mcmc"),
    ("kernels", "select", "update.select"),  # the rows in view, gathered
    ("kernels", "backward", "update.backward"),  # loss, error map and gradient through the renderer
    ("kernels", "step", "update.step"),  # chain rule, regulariser, Adam and noise on the rows in view
    ("renderer", "render", "render"),
)


def detail(rec, timing: StageTimes | None = None) -> StageTimes:
    """Time the sub-stages of :data:`DETAIL` that ``rec``'s policies have, into ``timing`` (default
    ``rec.timing``). Wraps bound methods of these instances only; a policy replaced later is not timed."""
    timing = timing or rec.timing
    for path, attr, name in DETAIL:
        obj = rec
        for part in filter(None, path.split(".")):  # "" is the Reconstructor itself
            obj = getattr(obj, part, None)
            if obj is None:
                break
        if obj is not None:
            _wrap(timing, obj, attr, name)
    return timing
