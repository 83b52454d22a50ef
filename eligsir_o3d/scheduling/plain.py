"""The plain policies that the ablations swap in: fixed-stride keyframes with uniform replay, fixed native
resolution, and new-space seeding with dense per-frame depth insertion. They are also the baseline behaviour."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..frame import Frame
from .base import FidelityPolicy, GrowthPolicy, MapContext, ViewPolicy
from .seeding import seeds_from_depth
from .support import ProbeConfig
from .views_trace import ViewsTrace


@dataclass
class StrideConfig:
    every: int = 5  # keep every k-th released frame
    newest_fraction: float = 0.25  # share of updates spent on the newest retained view
    max_views: int = 400  # retained views kept in memory (oldest evicted first beyond this)


class StrideKeyframes(ViewPolicy):
    """Fixed-stride keyframes; replay picks uniformly among retained views (plus a share for the newest)."""

    name = "stride"

    def __init__(self, cfg: StrideConfig | None = None):
        self.cfg = cfg or StrideConfig()
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


class FixedFidelity(FidelityPolicy):
    """Supervise at one fixed scale (1.0 = native resolution)."""

    name = "fixed"

    def __init__(self, scale: float = 1.0):
        self._scale = float(scale)

    def scale(self) -> float:
        return self._scale

    def counters(self) -> dict:
        return {"scale": self._scale}


@dataclass
class SeedingConfig:
    pixel_stride: int = 8  # seed one Gaussian per stride x stride block of unsupported depth pixels
    max_per_frame: int = 3000
    init_opacity: float = 0.5
    dense: bool = False  # ablation: insert at every frame whether or not the map already supports it


class NewSpaceSeeding(GrowthPolicy):
    """Seeds sparse depth-derived support where the map renders (almost) nothing; with ``dense`` it converts every
    released frame's depth into Gaussians (the "dense per-frame depth insertion" ablation)."""

    name = "seeding"

    def __init__(self, cfg: SeedingConfig | None = None, seed: int = 0, probe: ProbeConfig | None = None):
        self.cfg = cfg or SeedingConfig()
        self.probe = probe or ProbeConfig()  # the support render's scale and opacity threshold (config.support)
        self.rng = torch.Generator().manual_seed(seed)
        self.seeded = 0

    def on_frame(self, frame: Frame, admitted: bool, ctx: MapContext) -> int:
        if not admitted and not self.cfg.dense:
            return 0
        color, depth, cam = frame.at_scale(1.0, ctx.device)
        if self.cfg.dense or len(ctx.gmap) == 0:
            mask = depth > 0
        else:
            mask = unsupported_mask(frame, ctx, self.probe.scale, self.probe.alpha_min)
        room = ctx.max_gaussians - len(ctx.gmap)
        if room <= 0:
            return 0
        means, rgbs, scales = seeds_from_depth(color, depth, cam, frame.T_world_cam, mask, self.cfg.pixel_stride,
                                               min(self.cfg.max_per_frame, room), self.rng)
        if means.shape[0]:
            ctx.gmap.add(means, rgbs, scales, self.cfg.init_opacity)
        self.seeded += int(means.shape[0])
        return int(means.shape[0])

    def counters(self) -> dict:
        return {"seeded": self.seeded}

    def state_dict(self) -> dict:
        return {"rng": self.rng.get_state(), "seeded": self.seeded}

    def load_state_dict(self, state: dict) -> None:
        if "rng" in state:
            self.rng.set_state(state["rng"])
        self.seeded = int(state.get("seeded", 0))


@torch.no_grad()
def unsupported_mask(frame: Frame, ctx: MapContext, render_scale: float, alpha_threshold: float) -> torch.Tensor:
    """[H, W] bool at source resolution: pixels where the current map renders opacity below the threshold."""
    _, _, cam_s = frame.at_scale(render_scale, ctx.device)
    out = ctx.render(cam_s, frame.T_world_cam)
    low = (out.alpha < alpha_threshold).float()[None, None]
    up = torch.nn.functional.interpolate(low, size=(frame.camera.height, frame.camera.width), mode="nearest")
    return up[0, 0] > 0.5
