"""How far apart admitted views must be, tied to the compute budget: the spacing of Map-Guided View Scheduling's
pose pre-filter.

A view is worth what the updates it receives can fit. At the default budget a source frame buys a few updates at
1/4 scale, and the default spacing (``views.min_translation_m``, ``views.min_rotation_deg``) keeps every retained
view supplied: admitting views closer together there spreads the same updates thinner and loses on most
sequences. A larger budget (``--speed 0.1``, a faster machine under a calibrated cost model) buys many more
updates per frame, and a map trained on the same few views converges on them: more updates of it, at any scale,
stop paying (``benchmarks/quality/compute_returns.py``, docs/evaluation.md). So the spacing shrinks as the budget
grows, splitting the extra compute evenly (in ratio) between more views and more updates per view:

    u = (period_s - frame(N)) / update(pixels at 1/4 scale, N)        updates one source frame buys
    factor = min(1, sqrt(reference_updates / u))                      the thresholds' scale

with ``frame`` and ``update`` the run's cost model (the shipped fit where none drives the clock) and N the
Gaussians in the candidate's view. ``reference_updates`` is the per-frame count the default spacing was chosen
for; at or below it (every real-time run on the shipped cost model) the spacing is the default one.
"""

from __future__ import annotations

import math

from ..budget.cost import CostModel


class ViewSpacing:
    """The scale of the pose pre-filter's thresholds for the budget at hand (1: the configured spacing)."""

    def __init__(self, reference_updates: float = 8.0, scale: float = 0.25):
        if reference_updates < 0:
            raise ValueError(f"views.spacing_updates must be >= 0, got {reference_updates}")
        if not 0.0 < scale <= 1.0:
            raise ValueError(f"the spacing's pricing scale must lie in (0, 1], got {scale}")
        self.reference_updates = float(reference_updates)
        self.scale = float(scale)
        self.period_s: float | None = None
        self.cost: CostModel | None = None
        self.last = 1.0  # the factor of the last candidate judged
        self.smallest = 1.0  # the smallest factor so far

    @property
    def enabled(self) -> bool:
        return self.reference_updates > 0 and self.period_s is not None

    def attach(self, period_s: float | None, cost: CostModel | None) -> None:
        """The seconds one source frame grants and the cost model that prices the work (None: the shipped fit)."""
        if period_s is not None:
            self.period_s = float(period_s)
        self.cost = cost

    def updates_per_frame(self, pixels: int, gaussians: int) -> float:
        """Updates of ``pixels`` supervised pixels over ``gaussians`` Gaussians that one source frame buys."""
        c = self.cost or CostModel()
        left = self.period_s - c.frame(gaussians)
        return max(0.0, left) / max(c.update(pixels, gaussians), 1e-12)

    def could_shrink(self, pixels: int) -> bool:
        """Whether any map could make the spacing below 1 for updates of ``pixels`` pixels: an empty view buys
        the most updates (every Gaussian makes a frame and an update dearer)."""
        return self.enabled and self.updates_per_frame(pixels, 0) > self.reference_updates

    def factor(self, pixels: int, gaussians: int) -> float:
        """The thresholds' scale for a candidate whose update at the pricing scale supervises ``pixels`` pixels
        over ``gaussians`` Gaussians in view: ``min(1, sqrt(reference_updates / u))``; 1 when disabled."""
        f = 1.0
        if self.enabled:
            u = self.updates_per_frame(pixels, gaussians)
            if u > self.reference_updates:
                f = math.sqrt(self.reference_updates / u)
        self.last = f
        self.smallest = min(self.smallest, f)
        return f

    def counters(self) -> dict:
        return {"spacing": round(self.last, 4), "spacing_min": round(self.smallest, 4)}

    def state_dict(self) -> dict:
        return {"last": self.last, "smallest": self.smallest}

    def load_state_dict(self, state: dict) -> None:
        self.last = float(state.get("last", 1.0))
        self.smallest = float(state.get("smallest", 1.0))
