"""Where the mapper's time goes: wall seconds and calls per named stage.

The Reconstructor times its own stages with one :class:`StageTimes` (``rec.timing``): ``admission`` and
``growth`` (the per-frame fixed work of every integrated frame), ``update`` (optimisation updates) and ``tracking``
(a pose source); the pipeline adds ``decode`` (reading the recording, off the mapper's clock). metrics.json holds
:meth:`StageTimes.summary` as ``stage_times``. Two ``perf_counter`` calls per stage, nothing else.

Sub-stages (:data:`SUB_STAGES`: the support render, the voxel hash, view bookkeeping, the update's kernels, MCMC)
are marked where they run, with :meth:`StageTimes.sub`: the Reconstructor marks the calls it makes, a policy marks
its own steps with the timer its hook receives (``MapContext.timing``). They are timed only where the timer's
``detail`` is on (``benchmarks/budget/realtime_load.py --breakdown``); otherwise ``sub`` is one shared no-op
context. Nested stages are reported as they are: a sub-stage's seconds are also in its parent's.
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext


# every sub-stage name, for readers of a breakdown (``stage_times`` with ``detail`` on)
SUB_STAGES = {
    "admission.pose_filter": "the views' pose pre-filter (is the frame's pose close to a retained one)",
    "admission.view_bookkeeping": "a retained view's footprint cells, coverage and priorities",
    "support_render": "the support probe's render of the map at a new frame (shared by admission and growth)",
    "growth.voxel_hash": "the depth evidence's voxel-hash lookup",
    "growth.insert": "placing new Gaussians (seeds, insertions, relocation of dead ones)",
    "scheduling.select": "choosing the next update's view",
    "scheduling.feedback": "the views' microcell feedback from an update's error map",
    "update.select": "the rows in view, gathered",
    "update.backward": "loss, error map and gradient through the renderer",
    "update.step": "chain rule, regulariser, Adam and noise on the rows in view",
    "update.mcmc": "the growth policy's MCMC round after the step",
    "render": "every render of the map (training, support probe, evaluation)",
}

_NOTHING = nullcontext()


class StageTimes:
    """Accumulated wall seconds and calls per stage name; ``detail``: also time :meth:`sub` stages."""

    def __init__(self, detail: bool = False):
        self.detail = bool(detail)
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    @contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def sub(self, name: str):
        """The context of sub-stage ``name`` (one of :data:`SUB_STAGES`): timed as a stage where :attr:`detail` is
        on, a shared no-op context otherwise."""
        return self(name) if self.detail else _NOTHING

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
