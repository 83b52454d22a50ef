"""Map-Guided View Scheduling (paper Sec. "Map-Guided View Scheduling").

Admission is separated from long-term priority:
- admission: a pose pre-filter drops near-duplicates of retained views; the rest are compared with the current
  map (the fraction of their depth the map does not explain, from one low-resolution render); a maximum-gap rule
  admits the next non-redundant view when none was admitted for ``max_gap_s`` seconds.
- supervision: every admitted view is retained; an *active set* of the ``active_size`` highest-priority views gets
  most updates, the other retained views are replayed less often. Priorities follow the map: world-space microcells
  accumulate the error of the training renders, and a view's priority is the supervision its cells still need
  (weak or regressed cells raise it, well-reconstructed cells lower it) plus a bonus while the view is new.
  Priorities are refreshed every few updates, so retained views move in and out of the active set.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..core.camera import Camera
from ..core.frame import Frame
from ..render import RenderOutput
from .base import MapContext, ViewPolicy
from .microcells import Microcells
from .spacing import ViewSpacing
from .support import SupportProbe
from .view_config import ViewConfig
from .views_trace import ViewsTrace, pearson


@dataclass(eq=False)
class _View:
    frame: Frame
    cells: torch.Tensor  # [C] microcell ids of the view's footprint
    weights: torch.Tensor  # [C] share of the view's depth samples per cell
    updates: int = 0
    priority: float = 0.0
    last_error: float | torch.Tensor = float("nan")  # a plan's device scalar once folded
    last_update: int = -1  # the policy's update count when this view last supervised one (-1: never)
    plans: dict = field(default_factory=dict)  # (h, w) -> FeedbackPlan of the view's samples at that size


class MapGuidedViews(ViewPolicy):
    """Admission (pose pre-filter, map overlap, max-gap rule) + active/retained sets with map-driven priorities."""

    name = "map_guided"

    def __init__(self, cfg: ViewConfig | None = None, probe: SupportProbe | None = None,
                 cells: Microcells | None = None):
        self.cfg = cfg or ViewConfig()
        if self.cfg.retained_replay not in ("stalest", "priority"):
            raise ValueError(f"views.retained_replay must be 'stalest' or 'priority', got {self.cfg.retained_replay!r}")
        if self.cfg.drain_replay not in ("stalest", "policy"):
            raise ValueError(f"views.drain_replay must be 'stalest' or 'policy', got {self.cfg.drain_replay!r}")
        self.probe = probe or SupportProbe()
        self.cells = cells or Microcells(self.cfg.cells)
        self.fold_fn = None  # a kernel set's fused fold of the error into the cells (None: the torch rule)
        self.spacing = ViewSpacing(self.cfg.spacing_updates)
        self._views: list[_View] = []
        self._by_frame: dict[int, _View] = {}
        self.active: list[int] = []  # positions in self._views
        self._last_admit_ts: float | None = None
        self._since_refresh = 0
        self._flat = None  # (cells [F], weights [F], owner [F]) over all views; rebuilt when views change
        self.counts = {"released": 0, "admitted": 0, "pose_filtered": 0, "low_novelty": 0, "max_gap": 0,
                       "unchecked": 0}
        self.updates = 0  # training updates fed back so far (the trace's time axis)
        self._good = self.cfg.good_error  # the good-error level of the last refresh (``_good_level``)
        self.trace = ViewsTrace(self.cfg.trace_max)

    # ---- admission ------------------------------------------------------------------------------------------
    def admit(self, frame: Frame, ctx: MapContext) -> bool:
        self.counts["released"] += 1
        if not self._views:
            return self._admit(frame, ctx)
        # a closer spacing can only clear a candidate within the configured one: the budget is priced only then
        with ctx.timing.sub("admission.pose_filter"):
            redundant = (self.is_redundant(frame.T_world_cam)
                         and self.is_redundant(frame.T_world_cam, self._spacing(frame, ctx)))
        if redundant:
            self.counts["pose_filtered"] += 1
            return False
        gap = self._last_admit_ts is not None and frame.timestamp - self._last_admit_ts >= self.cfg.max_gap_s
        if not ctx.plan.check:  # under load (scheduling.load): no support render; the max-gap rule still admits
            if gap:
                self.counts["max_gap"] += 1
                return self._admit(frame, ctx)
            self.counts["unchecked"] += 1
            return False
        novelty = self.probe.check(frame, ctx).novelty()
        if novelty >= self.cfg.min_novelty:
            return self._admit(frame, ctx)
        if self._last_admit_ts is not None and frame.timestamp - self._last_admit_ts >= self.cfg.max_gap_s:
            self.counts["max_gap"] += 1
            return self._admit(frame, ctx)
        self.counts["low_novelty"] += 1
        return False

    def attach(self, period_s: float | None, cost=None) -> None:
        self.spacing.attach(period_s, cost)

    def _spacing(self, frame: Frame, ctx: MapContext) -> float:
        """The pose pre-filter's scale for this candidate under the current budget (:mod:`.spacing`)."""
        pixels = frame.camera.scaled(self.spacing.scale).pixels
        if not self.spacing.could_shrink(pixels):  # then the Gaussians in view (a culling pass) change nothing
            return self.spacing.factor(pixels, 0)
        return self.spacing.factor(pixels, ctx.in_view(frame.camera, frame.T_world_cam))

    def is_redundant(self, T_world_cam, factor: float = 1.0) -> bool:
        """True if some retained view is within both the translation and the rotation threshold (each scaled by
        ``factor``, the budget's spacing)."""
        if not self._views:
            return False
        T = np.asarray(T_world_cam)
        poses = np.stack([v.frame.T_world_cam for v in self._views])  # [V, 4, 4]
        dt = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1)
        # angle of R_v^T R: trace(R_v^T R) = sum of elementwise products
        tr = np.einsum("vij,ij->v", poses[:, :3, :3], T[:3, :3])
        ang = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
        return bool(np.any((dt < factor * self.cfg.min_translation_m) & (ang < factor * self.cfg.min_rotation_deg)))

    def _admit(self, frame: Frame, ctx: MapContext) -> bool:
        with ctx.timing.sub("admission.view_bookkeeping"):
            return self.retain(frame)

    def retain(self, frame: Frame) -> bool:
        """Retain ``frame`` as a training view without the admission test (its footprint cells, coverage and
        priorities): what an admitted frame gets; tools and benchmarks that fix the views call it directly."""
        cells, weights = self.cells.footprint(frame.depth, frame.camera, frame.T_world_cam)
        self.cells.add_coverage(cells, 1)
        view = _View(frame, cells, weights)
        self._views.append(view)
        self._by_frame[id(frame)] = view
        self._last_admit_ts = frame.timestamp
        self.counts["admitted"] += 1
        self.trace.add("admit", self.updates, view=int(frame.index))
        if len(self._views) > self.cfg.max_views:
            self._evict()
        self._flat = None
        self.refresh()
        return True

    def _evict(self) -> None:
        active = set(self.active)
        candidates = [i for i in range(len(self._views) - 1) if i not in active] or list(range(len(self._views) - 1))
        worst = min(candidates, key=lambda i: self._views[i].priority)
        view = self._views.pop(worst)
        self.trace.add("evict", self.updates, view=int(view.frame.index), priority=view.priority)
        self.cells.add_coverage(view.cells, -1)
        self._by_frame.pop(id(view.frame), None)
        view.frame.drop_cache()

    # ---- priorities -----------------------------------------------------------------------------------------
    def refresh(self) -> None:
        """Recompute every retained view's priority from its cells' need and rebuild the active set."""
        self._since_refresh = 0
        before = {int(self._views[i].frame.index) for i in self.active if i < len(self._views)}
        if not self._views:
            self.active = []
            return
        cells, weights, owner = self._flat_cells()
        c = self.cfg
        self._good = self._good_level(cells)
        need = self.cells.need(cells, self._good, c.regress_gain, c.regress_margin) * weights
        per_view = torch.zeros(len(self._views)).index_add_(0, owner, need)
        fresh = torch.tensor([max(0.0, 1.0 - v.updates / max(1, c.fresh_updates)) for v in self._views])
        prio = c.priority_floor + per_view + c.fresh_bonus * fresh
        for v, p in zip(self._views, prio.tolist()):
            v.priority = p
        k = min(c.active_size, len(self._views))
        self.active = torch.topk(prio, k).indices.sort().values.tolist()
        self._trace_refresh(before, prio, cells, weights, owner)

    def _good_level(self, cells: torch.Tensor) -> float:
        """The error level below which a cell needs no more supervision: ``good_error``, or the ``good_quantile``
        of the running errors of the measured cells in the retained views' footprints if higher."""
        level = self.cfg.good_error
        if self.cfg.good_quantile > 0:
            ids = torch.unique(cells)
            error, _, visits = self.cells.host()
            ids = ids[visits[ids] > 0]
            if ids.numel():
                level = max(level, float(torch.quantile(error[ids], self.cfg.good_quantile)))
        return level

    def _flat_cells(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(cells [F], weights [F], owner [F]): every retained view's footprint, concatenated (cached)."""
        if self._flat is None:
            owner = torch.cat([torch.full((v.cells.numel(),), i, dtype=torch.long) for i, v in enumerate(self._views)])
            self._flat = (torch.cat([v.cells for v in self._views]), torch.cat([v.weights for v in self._views]), owner)
        return self._flat

    def _view_errors(self, cells, weights, owner) -> tuple[torch.Tensor, torch.Tensor]:
        """Per retained view: footprint-weighted running error of its measured cells [V] (NaN: none measured) and
        the share of its footprint in cells above ``good_error`` [V]."""
        n = len(self._views)
        error, _, visits = self.cells.host()
        measured = (visits[cells] > 0).float() * weights
        err = torch.zeros(n).index_add_(0, owner, measured * error[cells])
        norm = torch.zeros(n).index_add_(0, owner, measured)
        weak = torch.zeros(n).index_add_(0, owner, (error[cells] > self._good).float() * weights)
        return torch.where(norm > 0, err / norm.clamp_min(1e-12), torch.full_like(err, float("nan"))), weak

    def _trace_refresh(self, before: set, prio: torch.Tensor, cells, weights, owner) -> None:
        """Promotions and demotions of this refresh, and how priority relates to the cells' measured error."""
        after = {int(self._views[i].frame.index) for i in self.active}
        if after == before and self.updates % (10 * self.cfg.refresh_every) != 0:
            return  # nothing moved: a refresh row only every 10th refresh
        err, weak = self._view_errors(cells, weights, owner)
        rank = torch.empty(len(prio), dtype=torch.long)
        rank[torch.argsort(prio, descending=True)] = torch.arange(len(prio))
        by_index = {int(v.frame.index): i for i, v in enumerate(self._views)}
        for event, group in (("promote", after - before), ("demote", before - after)):
            for idx in sorted(group):
                i = by_index.get(idx)
                if i is None:  # evicted since the last refresh
                    continue
                v = self._views[i]
                self.trace.add(event, self.updates, view=idx, priority=float(prio[i]), rank=int(rank[i]),
                               cell_error=float(err[i]), weak_share=float(weak[i]), replays=v.updates)
        self.trace.add("refresh", self.updates, retained=len(self._views), active=len(self.active),
                       corr=pearson(prio.tolist(), err.tolist()), moved=len(after ^ before), good=self._good,
                       prio_min=float(prio.min()), prio_max=float(prio.max()))

    def trace_rows(self) -> list[dict]:
        """The decision trace plus one ``final`` row per retained view (see :mod:`.views_trace`); no state changes."""
        if not self._views:
            return list(self.trace.rows)
        cells, weights, owner = self._flat_cells()
        err, weak = self._view_errors(cells, weights, owner)
        active = set(self.active)
        prio = torch.tensor([v.priority for v in self._views])
        rank = torch.empty(len(prio), dtype=torch.long)
        rank[torch.argsort(prio, descending=True)] = torch.arange(len(prio))
        final = [{"update": self.updates, "event": "final", "view": int(v.frame.index), "priority": v.priority,
                  "rank": int(rank[i]), "cell_error": float(err[i]), "weak_share": float(weak[i]),
                  "replays": v.updates, "active": int(i in active)} for i, v in enumerate(self._views)]
        return list(self.trace.rows) + final

    def priorities(self) -> list[float]:
        return [v.priority for v in self._views]

    def is_active(self, frame: Frame) -> bool:
        view = self._by_frame.get(id(frame))
        return view is not None and any(self._views[i] is view for i in self.active)

    # ---- selection and feedback -----------------------------------------------------------------------------
    def select(self, rng: torch.Generator) -> Frame:
        if not self._views:
            raise RuntimeError("no view has been admitted yet")
        if self.draining and self.cfg.drain_replay == "stalest":  # every retained view in turn
            return self._views[self._stalest(range(len(self._views)))].frame
        if self._since_refresh >= self.cfg.refresh_every:
            self.refresh()
        active = set(self.active)
        retained = [i for i in range(len(self._views)) if i not in active]
        pool = self.active
        if retained and float(torch.rand((), generator=rng)) >= self.cfg.active_share:
            if self.cfg.retained_replay == "stalest":
                return self._views[self._stalest(retained)].frame
            pool = retained
        p = torch.tensor([self._views[i].priority for i in pool], dtype=torch.float64)
        pick = pool[_draw_one(p / p.sum(), rng)]
        return self._views[pick].frame

    def _stalest(self, positions) -> int:
        """The view among ``positions`` whose last update is oldest; ties: the higher priority."""
        return min(positions, key=lambda i: (self._views[i].last_update, -self._views[i].priority))

    def bind(self, device, kernels) -> None:
        """Fold the training renders' errors on ``device`` (the map's), by ``kernels``' fused fold if it has one."""
        self.cells.to(device)
        self.fold_fn = kernels.fold_cells

    def poses_moved(self) -> None:
        for v in self._views:  # the pixels' cells follow the view's pose: located again at the next feedback
            v.plans.clear()

    def feedback(self, frame: Frame, out: RenderOutput, error: torch.Tensor, depth: torch.Tensor,
                 camera: Camera) -> None:
        """Splat the training render's per-pixel error [h, w] into the microcells its depth samples fall in."""
        view = self._by_frame.get(id(frame))
        if view is None:
            return
        key = (camera.height, camera.width)
        if key not in view.plans:
            view.plans[key] = self.cells.plan(depth, camera, frame.T_world_cam)
        plan = view.plans[key]
        self.cells.fold(plan, error.detach().reshape(-1), self.fold_fn)
        view.updates += 1
        self.updates += 1
        view.last_update = self.updates
        view.last_error = plan.last  # read (a host copy) only when saved
        self._since_refresh += 1

    @property
    def views(self) -> list[Frame]:
        return [v.frame for v in self._views]

    def counters(self) -> dict:
        return {**self.counts, **self.trace.counts, "retained": len(self._views), "active": len(self.active),
                "trace_dropped": self.trace.dropped, **self.spacing.counters()}

    # ---- persistence ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        views = [{"color": v.frame.color, "depth": v.frame.depth, "camera": v.frame.camera,
                  "T_world_cam": v.frame.T_world_cam, "timestamp": v.frame.timestamp, "index": v.frame.index,
                  "cells": v.cells, "weights": v.weights, "updates": v.updates, "priority": v.priority,
                  "last_error": float(v.last_error), "last_update": v.last_update} for v in self._views]
        # the active set and priorities of the last refresh decide the next picks: saved, not recomputed
        return {"views": views, "cells": self.cells.state_dict(), "last_admit_ts": self._last_admit_ts,
                "counts": dict(self.counts), "active": list(self.active), "since_refresh": self._since_refresh,
                "updates": self.updates, "trace": self.trace.state_dict(), "spacing": self.spacing.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.cells.load_state_dict(state["cells"])
        self._views, self._by_frame, self._flat = [], {}, None
        for d in state["views"]:
            frame = Frame(d["color"], d["depth"], d["camera"], d["T_world_cam"], d["timestamp"], d["index"])
            view = _View(frame, d["cells"], d["weights"], d["updates"], d.get("priority", 0.0),
                         d.get("last_error", float("nan")), last_update=int(d.get("last_update", -1)))
            self._views.append(view)
            self._by_frame[id(frame)] = view
        self._last_admit_ts = state["last_admit_ts"]
        self.counts.update(state.get("counts", {}))
        self.updates = int(state.get("updates", 0))
        self.trace.load_state_dict(state.get("trace", {}))
        self.spacing.load_state_dict(state.get("spacing", {}))
        if "active" in state:
            self.active = [int(i) for i in state["active"]]
            self._since_refresh = int(state["since_refresh"])
        else:
            self.refresh()


def _draw_one(p: torch.Tensor, rng: torch.Generator) -> int:
    """One index drawn with probabilities ``p`` (float64, non-negative, summing to 1): ``torch.multinomial(p, 1,
    generator=rng)``'s own draw for one sample (the argmax of ``p / q``, ``q`` exponential from ``rng``), the same
    pick and the same generator state, without its checks of ``p``."""
    q = torch.empty_like(p).exponential_(1.0, generator=rng)
    return int(torch.argmax(p / q))
