"""Fixed-stride keyframes (config key ``keyframes``): the plain view policy that the ``views`` ablation swaps in for
Map-Guided View Scheduling. Every ``every``-th released frame is kept; replay picks uniformly among the retained
views (plus a share for the newest)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.frame import Frame
from .base import MapContext, ViewPolicy


@dataclass
class KeyframesConfig:
    every: int = 5  # keep every k-th released frame
    newest_fraction: float = 0.25  # share of updates spent on the newest retained view
    max_views: int = 400  # retained views kept in memory (oldest evicted first beyond this)


class StrideKeyframes(ViewPolicy):
    """Fixed-stride keyframes; replay picks uniformly among retained views (plus a share for the newest)."""

    name = "stride"

    def __init__(self, cfg: KeyframesConfig | None = None):
        self.cfg = cfg or KeyframesConfig()
        self._views: list[Frame] = []
        self._released = 0

    def admit(self, frame: Frame, ctx: MapContext) -> bool:
        keep = self._released % self.cfg.every == 0
        self._released += 1
        if keep:
            self._views.append(frame)
            if len(self._views) > self.cfg.max_views:
                self._views.pop(0).drop_cache()
        return keep

    def select(self, rng: torch.Generator) -> Frame:
        if not self._views:
            raise RuntimeError("no view has been admitted yet")
        if float(torch.rand((), generator=rng)) < self.cfg.newest_fraction:
            return self._views[-1]
        return self._views[int(torch.randint(len(self._views), (), generator=rng))]

    @property
    def views(self) -> list[Frame]:
        return self._views

    def counters(self) -> dict:
        return {"released": self._released, "retained": len(self._views)}

    def state_dict(self) -> dict:
        return {"released": self._released, "views": list(self._views)}

    def load_state_dict(self, state: dict) -> None:
        self._released = int(state.get("released", 0))
        self._views = list(state.get("views", []))


StrideConfig = KeyframesConfig  # the class's name before the config vocabulary matched the key (issue 27)
