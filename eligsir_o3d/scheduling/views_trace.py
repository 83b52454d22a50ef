"""The trace of a view policy's decisions over a run (a results folder's views_trace.csv).

One row per event, in the order they happened; ``update`` is the policy's count of training updates so far:

- ``admit`` / ``evict``: a view enters or leaves the retained set;
- ``promote`` / ``demote``: a retained view enters or leaves the active supervision set at a priority refresh
  (``returns`` counts promotions of views that had been demoted before: retained views coming back);
- ``refresh``: one row per refresh with the set sizes and ``corr``, the Pearson correlation over the retained views
  between priority and ``cell_error`` (the footprint-weighted running training error of the view's microcells,
  measured cells only): whether replay priority follows the map's measured error;
- ``final``: one row per retained view at the end of the run (``replays``: its training updates, ``active``).

Per-view columns: ``view`` (the frame index), ``priority``, ``rank`` (0 = highest priority), ``cell_error``,
``weak_share`` (share of the view's footprint in cells whose running error is above the policy's good-error level),
``replays``. The trace is bounded (``max_rows``): once full, later events are counted in ``dropped``, not stored.
"""

from __future__ import annotations

import math


class ViewsTrace:
    """Bounded list of event rows (dicts) with counters of promotions, demotions and returns."""

    def __init__(self, max_rows: int = 50000):
        self.max_rows = int(max_rows)
        self.rows: list[dict] = []
        self.dropped = 0
        self.counts = {"promotions": 0, "demotions": 0, "returns": 0}
        self._demoted: set[int] = set()  # frame indices demoted at least once

    def add(self, event: str, update: int, **fields) -> None:
        if event == "promote":
            self.counts["promotions"] += 1
            if fields.get("view") in self._demoted:
                self.counts["returns"] += 1
        elif event == "demote":
            self.counts["demotions"] += 1
            self._demoted.add(fields.get("view"))
        if 0 < self.max_rows <= len(self.rows):
            self.dropped += 1
            return
        self.rows.append({"update": int(update), "event": event,
                          **{k: _round(v) for k, v in fields.items()}})

    def state_dict(self) -> dict:
        return {"rows": list(self.rows), "dropped": self.dropped, "counts": dict(self.counts),
                "demoted": sorted(self._demoted)}

    def load_state_dict(self, state: dict) -> None:
        self.rows = list(state.get("rows", []))
        self.dropped = int(state.get("dropped", 0))
        self.counts.update(state.get("counts", {}))
        self._demoted = set(int(v) for v in state.get("demoted", []))


def _round(v):
    if isinstance(v, float):
        return None if not math.isfinite(v) else round(v, 6)
    return v


def pearson(x: list[float], y: list[float]) -> float | None:
    """Pearson correlation of two equal-length lists (pairs with a non-finite member dropped); None when fewer than
    three pairs remain or either side is constant."""
    pairs = [(a, b) for a, b in zip(x, y) if math.isfinite(a) and math.isfinite(b)]
    if len(pairs) < 3:
        return None
    n = len(pairs)
    mx, my = sum(a for a, _ in pairs) / n, sum(b for _, b in pairs) / n
    sxy = sum((a - mx) * (b - my) for a, b in pairs)
    sxx = sum((a - mx) ** 2 for a, _ in pairs)
    syy = sum((b - my) ** 2 for _, b in pairs)
    if sxx <= 0 or syy <= 0:
        return None
    return sxy / math.sqrt(sxx * syy)
