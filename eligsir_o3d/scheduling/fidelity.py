"""Load-Adaptive Fidelity (paper Sec. "Load-Adaptive Fidelity").

The controller measures the recent cost of an update and the backlog of frames waiting for the mapper, and picks
the highest of the discrete scales (1/8, 1/4, 1/2, 1) whose predicted update cost fits the time one source frame
grants, shrunk while a backlog builds up; while no frame waits it does not go below ``idle_floor_scale`` (1/4):
only load takes it lower. The decision is reversible and has hysteresis: lowering needs
``down_patience`` consecutive votes, raising needs ``up_patience`` votes *and* that the next scale fits with
``up_margin`` slack, so measurement noise does not make it oscillate. Source images stay intact; the Reconstructor
resamples them (and scales the intrinsics) per update via ``Frame.at_scale``.

Cost comes from one of two places: measured seconds per update (real-time replay, the default), or a deterministic
cost model of the supervised pixels that the Reconstructor hands over with the load (:meth:`attach`, called by
``Reconstructor.set_load``), so runs are reproducible.
With measured seconds only the current scale's cost is fresh; other scales are predicted from it as
``cost * (pixels_other / pixels_now) ** gamma``, where the exponent ``gamma`` is learned at every scale change from
the costs measured just before and just after it (per-update overheads make gamma well below 1 on small images).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from ..budget.clock import DEFAULT_FRAME_PERIOD_S
from ..core.camera import Camera
from .base import FidelityPolicy
from .resolution import coarser_for


@dataclass
class FidelityConfig:
    scales: tuple[float, ...] = (0.125, 0.25, 0.5, 1.0)
    """The paper's discrete supervision scales (shares of the source resolution), ascending."""
    start_scale: float = 0.25
    """Scale before anything is measured; raised within a few updates if a finer one fits."""
    min_updates_per_frame: float = 12.0
    """A scale fits if this many of its updates fit in one frame period (lab: fidelity-min-updates)."""
    backlog_frames: float = 2.0
    """A backlog of this many frames halves the time granted per update."""
    idle_floor_scale: float = 0.25
    """Lowest scale used while no frame waits; only load takes the controller below it (lab: fidelity-idle-floor)."""
    floor_follows_camera: bool = True
    """On a camera larger than 640x480 the floor is multiplied by a power of two (``resolution.coarser_for``)."""
    floor_backlog: float = 0.5
    """Frames: below this backlog average no frame counts as waiting and the idle floor holds."""
    cost_ema: float = 0.3
    """Weight in [0, 1] of a new cost measurement in the running cost."""
    backlog_ema: float = 0.3
    """Weight in [0, 1] of a new backlog reading in the running backlog."""
    gamma_prior: float = 0.6
    """Exponent of cost ~ pixels^gamma before a scale change has measured it."""
    up_margin: float = 0.15
    """Raising the scale needs the next scale to fit with this share of slack."""
    up_patience: int = 5
    """Consecutive "raise" votes before the scale goes up one step."""
    down_patience: int = 2
    """Consecutive "lower" votes before the scale goes down to the fitting scale."""
    trace_every: int = 1
    """Keep every k-th decision in ``trace`` (``fidelity_trace.csv``)."""
    trace_max: int = 2000
    """Decisions kept in ``trace`` (0: no bound); beyond it every other one is dropped and the stride doubles."""
    fixed_scale: float = 1.0
    """Supervision scale when fidelity is ablated (1.0: native resolution, as in the paper)."""


class LoadAdaptiveFidelity(FidelityPolicy):
    """Backlog- and cost-driven choice of the supervision scale, with hysteresis; ``trace`` records every
    decision (update, backlog, scale, seconds, cumulative supervised pixels) for the paper's Fig. 6, thinned to at
    most ``trace_max`` entries on a long stream."""

    name = "load_adaptive"

    def __init__(self, cfg: FidelityConfig | None = None, camera: Camera | None = None):
        """``camera``: the stream's (its resolution sets the idle floor, ``floor_follows_camera``); None: the
        floor is ``idle_floor_scale``."""
        self.cfg = cfg or FidelityConfig()
        scales = tuple(sorted(float(s) for s in self.cfg.scales))
        if not scales or scales[0] <= 0 or scales[-1] > 1.0:
            raise ValueError(f"fidelity scales must lie in (0, 1], got {self.cfg.scales}")
        self.scales = scales
        self.level = min(range(len(scales)), key=lambda i: abs(scales[i] - self.cfg.start_scale))
        floor = coarser_for(self.cfg.idle_floor_scale, camera, self.cfg.floor_follows_camera)
        self.floor_level = min(range(len(scales)), key=lambda i: abs(scales[i] - floor))
        self.period_s = DEFAULT_FRAME_PERIOD_S  # until the Reconstructor hands over the real one (set_load)
        self.cost_fn: Callable[[int], float] | None = None
        self.cost: float | None = None  # EMA seconds per update at the current level
        self.pixels: list[int | None] = [None] * len(scales)  # supervised pixels of one update at each level
        self.gamma = float(self.cfg.gamma_prior)
        self.backlog = 0.0  # EMA of the backlog, frames
        self._obs_here = 0  # measurements since the last level change
        self._before: tuple[int, float] | None = None  # (pixels, cost) just before the last level change
        self._votes = 0  # > 0: consecutive raise votes; < 0: consecutive lower votes
        self._issued: int | None = None  # level handed out by the last scale()
        self.updates = 0
        self.supervised_pixels = 0
        self.by_scale: dict[str, int] = {}  # updates at each scale it issued; "explicit": refine()
        self.trace: list[dict] = []
        self.trace_stride = max(1, self.cfg.trace_every)  # doubles each time the trace is thinned (trace_max)

    def attach(self, period_s: float | None, cost_fn: Callable[[int], float] | None = None) -> None:
        """From ``Reconstructor.set_load``: the time one frame grants (after the replay speed) and, for a
        deterministic budget, the modelled seconds of an update of ``pixels`` supervised pixels (replaces measured
        seconds)."""
        if period_s is not None:
            self.period_s = float(period_s)
        self.cost_fn = cost_fn

    def scale(self) -> float:
        self._issued = self.level
        return self.scales[self.level]

    def current_scale(self) -> float:
        return self.scales[self.level]

    def observe(self, seconds: float, pixels: int, backlog: int) -> None:
        issued, self._issued = self._issued, None
        cost = float(self.cost_fn(pixels)) if self.cost_fn is not None else float(seconds)
        if issued == self.level:  # refine()/explicit scales bypass the controller and are not its measurements
            self.pixels[self.level] = int(pixels)
            fresh = self.cost is None or self._obs_here == 0  # the first measurement at a level replaces the prior
            self.cost = cost if fresh else (1 - self.cfg.cost_ema) * self.cost + self.cfg.cost_ema * cost
            self._obs_here += 1
            self._learn_gamma(pixels)
        a = self.cfg.backlog_ema
        self.backlog = (1 - a) * self.backlog + a * float(backlog)
        self.updates += 1
        self.supervised_pixels += int(pixels)
        key = f"{self.scales[issued]:g}" if issued is not None else "explicit"
        self.by_scale[key] = self.by_scale.get(key, 0) + 1
        self._decide()
        if self.updates % self.trace_stride == 0:
            self.trace.append({"update": self.updates, "backlog": float(backlog), "backlog_ema": self.backlog,
                               "scale": self.scales[self.level], "seconds": cost,
                               "supervised_mpix": self.supervised_pixels / 1e6})
            if 0 < self.cfg.trace_max < len(self.trace):
                self.trace_stride *= 2  # keep the decisions at multiples of the new stride
                self.trace = [d for d in self.trace if d["update"] % self.trace_stride == 0]

    # ---- cost prediction ------------------------------------------------------------------------------------
    def granted_s(self) -> float:
        """Seconds one update may take: the frame period split over the minimum updates, shrunk by backlog."""
        return self.period_s / self.cfg.min_updates_per_frame / (1.0 + self.backlog / self.cfg.backlog_frames)

    def predicted_cost(self, level: int) -> float | None:
        """Seconds of one update at ``level``: the cost model's, or the current level's measured cost carried over
        by the learned pixel exponent."""
        px = self._pixels_at(level)
        if self.cost_fn is not None:
            return None if px is None else float(self.cost_fn(px))
        here = self.pixels[self.level]
        if self.cost is None or px is None or not here:
            return None
        return self.cost * (px / here) ** self.gamma

    def _pixels_at(self, level: int) -> int | None:
        if self.pixels[level] is not None:
            return self.pixels[level]
        known = [i for i in range(len(self.scales)) if self.pixels[i] is not None]
        if not known:
            return None
        j = known[-1]
        return max(1, int(round(self.pixels[j] * (self.scales[level] / self.scales[j]) ** 2)))

    def _learn_gamma(self, pixels: int) -> None:
        """After 3 measurements at a new level, the exponent that links its cost to the level just left."""
        if self._before is None or self._obs_here != 3:
            return
        px0, c0 = self._before
        if px0 != pixels and c0 > 0 and self.cost > 0:
            g = math.log(self.cost / c0) / math.log(pixels / px0)
            self.gamma = 0.5 * self.gamma + 0.5 * min(1.5, max(0.0, g))

    # ---- the decision ---------------------------------------------------------------------------------------
    def _decide(self) -> None:
        budget = self.granted_s()
        costs = [self.predicted_cost(i) for i in range(len(self.scales))]
        floor = self.floor_level if self.backlog < self.cfg.floor_backlog else 0
        target = max([i for i, c in enumerate(costs) if c is not None and c <= budget] + [floor])
        if target < self.level:
            self._votes = min(self._votes, 0) - 1
            if -self._votes >= self.cfg.down_patience:
                self._switch(target)
        elif target > self.level and (self.level + 1 <= floor or self._fits(costs[self.level + 1], budget)):
            self._votes = max(self._votes, 0) + 1
            if self._votes >= self.cfg.up_patience:
                self._switch(self.level + 1)
        else:
            self._votes = 0

    def _fits(self, cost: float | None, budget: float) -> bool:
        return cost is not None and cost <= budget * (1.0 - self.cfg.up_margin)

    def _switch(self, level: int) -> None:
        if self.cost is not None and self.pixels[self.level]:
            self._before = (self.pixels[self.level], self.cost)
            self.cost = self.predicted_cost(level)  # a prior for the new level until its own measurements arrive
        self.level, self._votes, self._obs_here = level, 0, 0

    def at_lowest_scale(self) -> bool:
        return self.level == 0

    def counters(self) -> dict:
        return {"scale": self.scales[self.level], "updates_by_scale": dict(self.by_scale)}

    # ---- persistence ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"level": self.level, "period_s": self.period_s, "cost": self.cost, "pixels": list(self.pixels),
                "gamma": self.gamma, "backlog": self.backlog, "votes": self._votes, "updates": self.updates,
                "obs_here": self._obs_here, "before": None if self._before is None else list(self._before),
                "supervised_pixels": self.supervised_pixels, "trace": list(self.trace),
                "trace_stride": self.trace_stride,
                "by_scale": dict(self.by_scale)}

    def load_state_dict(self, state: dict) -> None:
        self.level, self.period_s = int(state["level"]), float(state["period_s"])
        self.cost, self.pixels, self.gamma = state["cost"], list(state["pixels"]), float(state["gamma"])
        self.backlog, self._votes = float(state["backlog"]), int(state["votes"])
        self._obs_here = int(state.get("obs_here", 0))
        before = state.get("before")
        self._before = None if before is None else (int(before[0]), float(before[1]))
        self.updates, self.supervised_pixels = int(state["updates"]), int(state["supervised_pixels"])
        self.trace = list(state.get("trace", []))
        self.trace_stride = int(state.get("trace_stride", max(1, self.cfg.trace_every)))
        self.by_scale = dict(state.get("by_scale", {}))
