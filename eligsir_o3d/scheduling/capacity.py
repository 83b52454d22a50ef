"""How many Gaussians the budget can carry: the map-size cap of Targeted Geometry Growth tied to the compute budget.

A Gaussian is not free: every update and every integrated frame pays for each one it covers (the cost model's
``gaussian_s`` and ``pixel_gaussian_s`` terms); with view culling (``config.optim.cull``, the default) an update
covers the Gaussians that can reach its view, so N below counts the Gaussians *in one view*, and the map's total
may grow wherever a view leaves room (``TargetedGrowth.cap``), up to ``config.max_gaussians`` (memory: ~200
bytes per Gaussian with its Adam state). A map that grows until updates become rare trains badly; a map held small stays
blurry however many updates it gets. The budget cap lets the map grow only while one source frame still buys
``min_updates`` updates of ``pixels`` supervised pixels (the growth policy prices them at ``growth.budget_scale``):

    frame(N) + min_updates * update(pixels, N) <= period_s

with ``frame`` and ``update`` the cost model's, solved for N (the Gaussians in view). At a tenth of real time a frame grants ten times the
seconds, so the map may grow several times larger; on a faster machine (a calibrated, cheaper model) likewise. The
cap never exceeds ``config.max_gaussians`` (memory) and never drops below ``min_gaussians`` (a map must exist).
"""

from __future__ import annotations

from ..budget.cost import CostModel


class BudgetCap:
    """The largest map size that still leaves ``min_updates`` updates per source frame (0: no budget cap)."""

    def __init__(self, min_updates: float = 0.0, min_gaussians: int = 1000):
        if min_updates < 0:
            raise ValueError(f"growth.budget_updates must be >= 0, got {min_updates}")
        self.min_updates = float(min_updates)
        self.min_gaussians = int(min_gaussians)
        self.period_s: float | None = None
        self.cost: CostModel | None = None

    def attach(self, period_s: float | None, cost: CostModel | None) -> None:
        """The seconds one source frame grants and the cost model that prices the work (None: the shipped model,
        the reference machine's fit, e.g. under real-time replay where no model drives the clock)."""
        if period_s is not None:
            self.period_s = float(period_s)
        self.cost = cost

    def cap(self, max_gaussians: int, pixels: int) -> int:
        """The map-size cap for updates of ``pixels`` supervised pixels."""
        if self.min_updates <= 0 or self.period_s is None or pixels <= 0:
            return int(max_gaussians)
        c = self.cost or CostModel()
        m = self.min_updates
        fixed = c.frame_s + m * (c.update_s + pixels * c.pixel_s)
        per_gaussian = c.gaussian_s + m * (c.gaussian_s + pixels * c.pixel_gaussian_s)
        if per_gaussian <= 0:
            return int(max_gaussians)
        n = int((self.period_s - fixed) / per_gaussian)
        return int(min(max_gaussians, max(self.min_gaussians, n)))
