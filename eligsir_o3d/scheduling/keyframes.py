"""Fixed-stride keyframes (config key ``keyframes``): the plain view policy that the ``views`` ablation swaps in for
Map-Guided View Scheduling. Every ``every``-th released frame is kept; replay picks uniformly among the retained
views (plus a share for the newest)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.frame import Frame
from .base import MapContext, ViewPolicy
from .views_trace import ViewsTrace


@dataclass
class KeyframesConfig:
    every: int = 5
    """Keep every k-th released frame as a training view."""
    newest_fraction: float = 0.25
    """Share of updates spent on the newest retained view; the rest are drawn uniformly from the others."""
    max_views: int = 400
    """Retained views kept in memory; beyond this the oldest is evicted first."""


class StrideKeyframes(ViewPolicy):
    """Fixed-stride keyframes; replay picks uniformly among retained views (plus a share for the newest)."""

    name = "stride"

    def __init__(self, cfg: KeyframesConfig | None = None):
        self.cfg = cfg or KeyframesConfig()
        self._views: list[Frame] = []
        self._released = 0
        self._replays: dict[int, int] = {}  # frame index -> training updates it supervised (views_trace.csv)
        self.trace = ViewsTrace()

    def admit(self, frame: Frame, ctx: MapContext) -> bool:
        keep = self._released % self.cfg.every == 0
        self._released += 1
        if keep:
            self._views.append(frame)
            self.trace.add("admit", sum(self._replays.values()), view=int(frame.index))
            if len(self._views) > self.cfg.max_views:
                old = self._views.pop(0)
                self.trace.add("evict", sum(self._replays.values()), view=int(old.index))
                old.drop_cache()
        return keep

    def select(self, rng: torch.Generator) -> Frame:
        if not self._views:
            raise RuntimeError("no view has been admitted yet")
        if float(torch.rand((), generator=rng)) < self.cfg.newest_fraction:
            pick = self._views[-1]
        else:
            pick = self._views[int(torch.randint(len(self._views), (), generator=rng))]
        self._replays[int(pick.index)] = self._replays.get(int(pick.index), 0) + 1
        return pick

    def trace_rows(self) -> list[dict]:
        """Admissions and evictions, then one ``final`` row per retained view with its replays."""
        n = sum(self._replays.values())
        return list(self.trace.rows) + [{"update": n, "event": "final", "view": int(f.index),
                                         "replays": self._replays.get(int(f.index), 0)} for f in self._views]

    @property
    def views(self) -> list[Frame]:
        return self._views

    def counters(self) -> dict:
        return {"released": self._released, "retained": len(self._views)}

    def state_dict(self) -> dict:
        return {"released": self._released, "views": list(self._views), "replays": dict(self._replays),
                "trace": self.trace.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self._released = int(state.get("released", 0))
        self._views = list(state.get("views", []))
        self._replays = {int(k): int(v) for k, v in state.get("replays", {}).items()}
        self.trace.load_state_dict(state.get("trace", {}))


