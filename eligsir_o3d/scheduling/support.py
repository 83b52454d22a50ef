"""Where does the current map support a new observation? One low-resolution render, shared by admission
(view overlap, Map-Guided View Scheduling) and growth (unsupported / misplaced depth, Targeted Geometry Growth)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.camera import Camera
from ..core.frame import Frame
from .base import MapContext
from .resolution import coarser_for


@dataclass
class SupportConfig:
    scale: float = 0.25
    """Share of the source resolution at which the support check renders a 640x480 stream."""
    follow_camera: bool = True
    """Larger cameras render at ``scale`` times a power of two (``resolution.coarser_for``); false: ``scale``."""
    alpha_min: float = 0.5
    """Rendered opacity below this means the map does not support the pixel."""
    depth_tol_m: float = 0.05
    """Metres: rendered depth farther than ``depth_tol_m + depth_tol_rel * z`` from the observation is misplaced."""
    depth_tol_rel: float = 0.03
    """Share of the observed depth added to ``depth_tol_m`` (depth noise grows with distance)."""

    def scale_for(self, camera: Camera) -> float:
        """The support render's scale for frames of ``camera``."""
        return coarser_for(self.scale, camera, self.follow_camera)




@dataclass
class Support:
    """The probe render of one frame against the current map, at the probe's scale."""

    color: torch.Tensor  # [h, w, 3] observed colour
    depth: torch.Tensor  # [h, w] observed depth, metres (0 = none)
    camera: Camera
    unsupported: torch.Tensor  # [h, w] bool: valid depth where the rendered opacity is low
    misplaced: torch.Tensor  # [h, w] bool: valid depth, opaque render, but rendered depth disagrees

    @property
    def valid(self) -> torch.Tensor:
        return self.depth > 0

    def novelty(self) -> float:
        """Fraction of the valid depth pixels that the map does not explain (unsupported or misplaced)."""
        v = self.valid
        n = int(v.sum())
        return float((self.unsupported | self.misplaced).sum()) / n if n else 0.0


class SupportProbe:
    """Renders a frame's view of the map at a low scale; the result is cached until the map changes."""

    def __init__(self, cfg: SupportConfig | None = None):
        self.cfg = cfg or SupportConfig()
        self._key = None
        self._value: Support | None = None

    @torch.no_grad()
    def check(self, frame: Frame, ctx: MapContext) -> Support:
        scale = self.cfg.scale_for(frame.camera) * ctx.plan.probe_factor  # lower under load (scheduling.load)
        key = (id(frame), frame.index, len(ctx.gmap), ctx.updates, scale)
        if key == self._key and self._value is not None:
            return self._value
        color, depth, cam = frame.at_scale(scale, "cpu")
        valid = depth > 0
        if len(ctx.gmap) == 0:
            unsupported, misplaced = valid.clone(), torch.zeros_like(valid)
        else:
            with ctx.timing.sub("support_render"):
                out = ctx.render(cam, frame.T_world_cam)
            dev = out.alpha.device  # the masks are made where the render is; only they come to the host
            observed = depth if dev.type == "cpu" else frame.at_scale(scale, dev)[1]
            unsupported, misplaced = support_masks(out.alpha.detach(), out.depth.detach(), observed, self.cfg,
                                                   pack=dev.type != "cpu")
        self._key, self._value = key, Support(color, depth, cam, unsupported, misplaced)
        return self._value


def support_masks(alpha: torch.Tensor, rdepth: torch.Tensor, depth: torch.Tensor, cfg: SupportConfig,
                  pack: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(unsupported, misplaced) [h, w] bool masks on the host from a render's opacity ``alpha`` and depth ``rdepth``
    [h, w] and the observed ``depth`` [h, w] (metres, 0 = none), all on one device. ``pack``: the two masks cross
    to the host as one byte per pixel (one copy instead of two float images)."""
    valid = depth > 0
    opaque = alpha >= cfg.alpha_min
    unsupported = valid & ~opaque
    tol = cfg.depth_tol_m + cfg.depth_tol_rel * depth
    misplaced = valid & opaque & ((rdepth - depth).abs() > tol)
    if not pack:
        return unsupported.cpu(), misplaced.cpu()
    code = (unsupported.to(torch.uint8) | (misplaced.to(torch.uint8) << 1)).cpu()
    return (code & 1) > 0, (code & 2) > 0
