"""Depth-derived Gaussian seeds (config key ``seeding``): back-project a strided subset of depth pixels into
world-space Gaussians (:func:`seeds_from_depth`, shared with Targeted Geometry Growth), and the plain growth policy
that the ``growth`` ablation swaps in (:class:`NewSpaceSeeding`: seeds where the map renders nothing, or with
``dense`` every frame's depth)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.camera import Camera
from ..core.frame import Frame
from .base import GrowthPolicy, MapContext
from .support import SupportConfig


def seeds_from_depth(color: torch.Tensor, depth: torch.Tensor, camera: Camera, T_world_cam, mask: torch.Tensor,
                     stride: int, max_points: int, generator: torch.Generator | None = None,
                     footprint: float = 0.5):
    """Seeds at masked, valid depth pixels on a ``stride`` grid (at most ``max_points``, chosen at random).

    color [H, W, 3], depth [H, W] metres, mask [H, W] bool. Returns (means [M, 3] world, rgbs [M, 3], scales [M]):
    each seed's scale (standard deviation, metres) is ``footprint`` times the width of a stride x stride pixel block
    at its depth: at 0.5 the 2-sigma extents of neighbouring seeds just touch, so the seeds cover the surface.
    """
    sel = torch.zeros_like(mask)
    sel[stride // 2::stride, stride // 2::stride] = True
    sel &= mask & (depth > 0)
    vs, us = torch.nonzero(sel, as_tuple=True)
    if vs.numel() > max_points:
        pick = torch.randperm(vs.numel(), generator=generator, device=vs.device)[:max_points] if generator is None \
            else torch.randperm(vs.numel(), generator=generator)[:max_points].to(vs.device)
        vs, us = vs[pick], us[pick]
    z = depth[vs, us]
    means = camera.unproject(us, vs, z, T_world_cam)
    scales = z * stride / (0.5 * (camera.fx + camera.fy)) * footprint
    return means, color[vs, us], scales


@dataclass
class SeedingConfig:
    pixel_stride: int = 8
    """Source pixels: one Gaussian per stride x stride block of unsupported depth pixels."""
    max_per_frame: int = 3000
    """Bound on the Gaussians one frame may seed."""
    init_opacity: float = 0.5
    """Opacity in (0, 1) of a seeded Gaussian."""
    dense: bool = False
    """Seed every frame whether or not the map already supports it (an ablation)."""


class NewSpaceSeeding(GrowthPolicy):
    """Seeds sparse depth-derived support where the map renders (almost) nothing; with ``dense`` it converts every
    released frame's depth into Gaussians (the "dense per-frame depth insertion" ablation)."""

    name = "seeding"

    def __init__(self, cfg: SeedingConfig | None = None, seed: int = 0, probe: SupportConfig | None = None):
        self.cfg = cfg or SeedingConfig()
        self.probe = probe or SupportConfig()  # the support render's scale and opacity threshold (config.support)
        self.rng = torch.Generator().manual_seed(seed)
        self.seeded = 0

    def on_frame(self, frame: Frame, admitted: bool, ctx: MapContext) -> int:
        if not admitted and not self.cfg.dense:
            return 0
        color, depth, cam = frame.at_scale(1.0, ctx.device)
        if self.cfg.dense or len(ctx.gmap) == 0:
            mask = depth > 0
        else:
            mask = unsupported_mask(frame, ctx, self.probe.scale_for(frame.camera), self.probe.alpha_min)
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
