"""Coarse-to-fine supervision for a schedule of known length (the offline reference, DashGaussian-style): the first
updates at a coarse scale, where an update is cheap and fits the low frequencies, the last ones at full resolution.

Measured on the real recordings at hand, a fixed number of updates buys more held-out quality when most of them are
coarse (see :data:`DEFAULT_STAGES`); the schedule also costs less time, so a fixed time buys more updates.
"""

from __future__ import annotations

from .base import FidelityPolicy

# (scale, share of the schedule), in order; the shares add up to 1
DEFAULT_STAGES: tuple[tuple[float, float], ...] = ((0.25, 0.4), (0.5, 0.3), (1.0, 0.3))


class CoarseToFine(FidelityPolicy):
    """Scale of the next update from the progress through a ``total``-update schedule, stage by stage."""

    name = "coarse_to_fine"

    def __init__(self, total: int, stages: tuple[tuple[float, float], ...] = DEFAULT_STAGES):
        if total < 1:
            raise ValueError(f"coarse-to-fine schedule: total updates must be >= 1, got {total}")
        shares = [float(s) for _, s in stages]
        if not stages or any(not 0 < sc <= 1 for sc, _ in stages) or any(s < 0 for s in shares) \
                or abs(sum(shares) - 1.0) > 1e-6:
            raise ValueError(f"coarse-to-fine stages must be (scale in (0, 1], share >= 0) with shares summing "
                             f"to 1, got {stages}")
        self.total = int(total)
        self.stages = tuple((float(sc), float(s)) for sc, s in stages)
        self.updates = 0
        self.by_scale: dict[str, int] = {}

    def scale(self) -> float:
        p = self.updates / self.total
        edge = 0.0
        for sc, share in self.stages:
            edge += share
            if p < edge - 1e-12:
                return sc
        return self.stages[-1][0]

    def observe(self, seconds: float, pixels: int, backlog: int) -> None:
        key = f"{self.scale():g}"
        self.by_scale[key] = self.by_scale.get(key, 0) + 1
        self.updates += 1

    def counters(self) -> dict:
        return {"total": self.total, "stages": [list(s) for s in self.stages], "updates_by_scale": dict(self.by_scale)}

    def state_dict(self) -> dict:
        return {"updates": self.updates, "by_scale": dict(self.by_scale)}

    def load_state_dict(self, state: dict) -> None:
        self.updates = int(state["updates"])
        self.by_scale = dict(state.get("by_scale", {}))
