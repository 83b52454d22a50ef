"""Which pixels an update supervises at a reduced scale: area averages, or point samples of the source image.

At 1/k scale (Load-Adaptive Fidelity's choice) an update sees (W/k) x (H/k) pixels. *Area* supervision fits the
map to k x k averages of the source image: what a recording whose poses and depth agree with its colour to a few
pixels can teach (the average also averages that misregistration and the sensor's noise). *Point* supervision fits
it to every k-th source pixel from a random phase per update, rendered with the source resolution's low-pass: the
same number of pixels and the same cost, but over updates the map sees every source pixel unblurred, so it can hold
the detail of data that agrees at full resolution (rendered sequences; lab: supervision-coherence).

Which one a sequence gets is measured, not configured per dataset: :func:`detail_coherence` warps the last view
measured into a newly admitted one (the later view's depth, both given poses) and correlates the two
images' detail bands (image minus its box blur). Detail that agrees across views scores near 1, detail that pose,
depth-colour registration or noise scramble scores near 0. A pair's views are at least the pose filter's default
spacing apart (5 cm or 5 degrees), whatever spacing the budget lets the views have (closer views agree more: the
kitchen's at ``--speed 0.1`` measured 0.72 against 0.44 in real time; the offline reference admits every frame). After
``pairs`` pairs the median decides, once for the run: point supervision at or above ``coherence_min``, else area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..core.camera import Camera, invert_pose, rotation_angle_deg
from ..core.frame import Frame
from ..core.gaussians import EPS2D

MODES = ("auto", "area", "point")


@dataclass
class SupervisionConfig:
    mode: str = "auto"
    """``auto`` (decided per run from the views' coherence), ``area`` (pixel averages) or ``point`` (samples)."""
    pairs: int = 2
    """Admitted view pairs whose median coherence decides ``auto``."""
    coherence_min: float = 0.6
    """Median detail-band coherence in [0, 1] at or above which ``auto`` takes point samples (lab: supervision-coherence)."""
    band_px: int = 4
    """Source pixels: the detail band is the image minus its band_px x band_px box blur."""
    max_pixels: int = 80_000
    """Pixels: the coherence uses a centre crop of the later view of at most this many."""
    pair_translation_m: float = 0.05
    """Metres: a pair's views are at least this far apart, or turned by ``pair_rotation_deg``."""
    pair_rotation_deg: float = 5.0
    """Degrees: the turn that makes two views a pair when they are closer than ``pair_translation_m``."""


@dataclass
class Sample:
    """One update's supervision: colour [h, w, 3], depth [h, w], the camera of those pixels, the screen-space
    low-pass [px^2] to render them with, and the camera whose resolution the map is thereby fitted at."""

    color: torch.Tensor
    depth: torch.Tensor
    camera: Camera
    low_pass: float
    fitted: Camera


def _box_blur(img: torch.Tensor, b: int) -> torch.Tensor:  # [H, W, C] -> [H, W, C], edges replicated
    t = img.permute(2, 0, 1)[None]
    t = F.pad(t, (b // 2, (b - 1) // 2, b // 2, (b - 1) // 2), mode="replicate")
    return F.avg_pool2d(t, b, 1)[0].permute(1, 2, 0)


@torch.no_grad()
def detail_coherence(later: Frame, earlier: Frame, band_px: int = 4, max_pixels: int = 80_000) -> float | None:
    """How well the detail of ``earlier`` predicts that of ``later`` at their poses (a correlation in [-1, 1]).

    ``earlier``'s colour is warped into ``later`` through ``later``'s depth and both frames' ``T_world_cam``; pixels
    without depth, outside ``earlier``'s image, occluded there (its depth disagrees by more than 1 cm + 3 %) or
    within ``band_px`` of such a pixel are left out. On the rest, with ``d = image - box_blur(image)``:
    ``1 - mean((d_later - d_warped)^2) / (mean(d_later^2) + mean(d_warped^2))``. None when fewer than 1000 pixels
    overlap (nothing to measure)."""
    H, W = later.depth.shape
    side = math.sqrt(max(1.0, max_pixels / (H * W)))  # a centre crop of at most max_pixels
    h, w = min(H, int(H * side)), min(W, int(W * side))
    y0, x0 = (H - h) // 2, (W - w) // 2
    cj = earlier.camera
    z = later.depth[y0:y0 + h, x0:x0 + w]
    v, u = torch.meshgrid(torch.arange(y0, y0 + h), torch.arange(x0, x0 + w), indexing="ij")
    T_earlier_later = invert_pose(earlier.T_world_cam) @ later.T_world_cam
    q = later.camera.unproject(u.reshape(-1), v.reshape(-1), z.reshape(-1), T_earlier_later).double()
    zj = q[:, 2].clamp_min(1e-6)
    uj, vj = q[:, 0] / zj * cj.fx + cj.cx, q[:, 1] / zj * cj.fy + cj.cy
    Hj, Wj = earlier.depth.shape
    grid = torch.stack([(uj + 0.5) / Wj * 2 - 1, (vj + 0.5) / Hj * 2 - 1], -1).float().reshape(1, h, w, 2)
    warped = F.grid_sample(earlier.color.permute(2, 0, 1)[None], grid, mode="bilinear", align_corners=False)
    warped = warped[0].permute(1, 2, 0)
    dj = F.grid_sample(earlier.depth[None, None], grid, mode="nearest", align_corners=False).reshape(-1).double()
    inside = (uj > 1) & (uj < Wj - 2) & (vj > 1) & (vj < Hj - 2) & (q[:, 2] > 0.05)
    seen = inside & ((dj - q[:, 2]).abs() < 0.03 * q[:, 2] + 0.01) & (z.reshape(-1) > 0)
    bad = (~seen).reshape(1, 1, h, w).float()
    ok = F.max_pool2d(bad, 2 * band_px + 1, 1, band_px)[0, 0] == 0  # away from every left-out pixel
    if int(ok.sum()) < 1000:
        return None
    mine = later.color[y0:y0 + h, x0:x0 + w]
    d_mine = (mine - _box_blur(mine, band_px))[ok]
    d_warp = (warped - _box_blur(warped, band_px))[ok]
    energy = float((d_mine ** 2).mean() + (d_warp ** 2).mean())
    if energy <= 0.0:
        return None  # no detail in either (a flat wall): nothing to measure
    return 1.0 - float(((d_mine - d_warp) ** 2).mean()) / energy


class SupervisionGrid:
    """Area or point supervision for a run (module docstring). State: the coherences measured so far, the last
    admitted view (until the decision) and the decision ("area" / "point"; None while undecided, which samples
    areas)."""

    name = "coherence-gated"

    def __init__(self, cfg: SupervisionConfig | None = None):
        self.cfg = cfg or SupervisionConfig()
        if self.cfg.mode not in MODES:
            raise ValueError(f"supervision.mode {self.cfg.mode!r}: choose from {', '.join(MODES)}")
        self.coherence: list[float] = []
        self.decided: str | None = None if self.cfg.mode == "auto" else self.cfg.mode
        self._last: Frame | None = None

    @property
    def mode(self) -> str:
        return self.decided or "area"

    def on_admitted(self, frame: Frame) -> bool:
        """A view was admitted: measure its coherence with the last view measured (or the first), if it is far
        enough from it, and decide after enough pairs. True when this call decided."""
        if self.decided is not None:
            return False
        if self._last is not None:
            if not self._apart(frame.T_world_cam, self._last.T_world_cam):
                return False  # too close to tell misregistration from agreement: wait for a view further on
            c = detail_coherence(frame, self._last, self.cfg.band_px, self.cfg.max_pixels)
            if c is not None:
                self.coherence.append(c)
        self._last = frame
        if len(self.coherence) >= self.cfg.pairs:
            self.decided = "point" if float(np.median(self.coherence)) >= self.cfg.coherence_min else "area"
            self._last = None
            return True
        return False

    def seed_scale(self, update_scale: float) -> float | None:
        """The image scale whose pixels the growth policy spaces new seeds in. With point samples, the updates'
        scale: a region is seeded as finely as it is supervised (the growth's 4-pixel stride then means 4 supervised
        pixels, e.g. 8 source pixels at 1/2-scale updates instead of 16). With area averages None, the support
        probe's scale: fine seeds from depth that disagrees with its colour by pixels fit that noise (lab: growth-seed-detail)."""
        return update_scale if self.mode == "point" else None

    def _apart(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        moved = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
        turned = rotation_angle_deg(T_a[:3, :3].T @ T_b[:3, :3])
        return moved >= self.cfg.pair_translation_m or turned >= self.cfg.pair_rotation_deg

    def sample(self, frame: Frame, scale: float, rng: torch.Generator, device) -> Sample:
        """The pixels an update at ``scale`` supervises. Point sampling needs a whole step (1 / scale); at any other
        scale, and at full resolution, the update sees the area-averaged pyramid level (:meth:`Frame.at_scale`)."""
        step = round(1.0 / scale)
        if self.mode == "point" and step > 1 and abs(step * scale - 1.0) < 1e-6:
            px, py = torch.randint(0, step, (2,), generator=rng).tolist()
            color, depth, cam = frame.point_sampled(step, px, py, device)
            return Sample(color, depth, cam, EPS2D / (step * step), frame.camera)
        color, depth, cam = frame.at_scale(scale, device)
        return Sample(color, depth, cam, EPS2D, cam)

    def counters(self) -> dict:
        med = float(np.median(self.coherence)) if self.coherence else None
        return {"mode": self.mode, "decided": self.decided is not None, "pairs": len(self.coherence),
                "coherence_median": None if med is None else round(med, 3)}

    def state_dict(self) -> dict:
        return {"coherence": list(self.coherence), "decided": self.decided, "last": self._last}

    def load_state_dict(self, state: dict) -> None:
        self.coherence = [float(c) for c in state.get("coherence", [])]
        self.decided = state.get("decided", None if self.cfg.mode == "auto" else self.cfg.mode)
        self._last = state.get("last")
