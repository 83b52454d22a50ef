"""Targeted Geometry Growth (paper Sec. "Targeted Geometry Growth").

Depth has two roles. It supervises the geometry that exists (the depth term of the loss, nothing here), and it is
evidence for growing the representation, which this policy controls:
- sparse structural support: space seen for the first time (voxels of the evidence store that no earlier view has
  observed) that the map does not support gets a bounded set of sparse depth-derived Gaussians;
- progressive growth: where an admitted view finds already-observed space unsupported (low rendered opacity) or
  misplaced (rendered depth disagrees beyond a tolerance), its voxels collect one vote per *distinct* view; only
  voxels with ``min_views`` votes receive finer Gaussians, and a view that finds a voxel explained takes a vote away;
- population refinement: 3DGS-MCMC relocation of dead Gaussians, replacement and densification under the cap.

The evidence store is a :class:`VoxelHash` (an Open3D hash map) with per-voxel votes and the last voting view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..core.camera import Camera
from ..core.frame import Frame
from ..kernels.base import StepTerms
from ..render import RenderOutput
from .base import GrowthPolicy, MapContext
from .capacity import BudgetCap
from .mcmc import MCMCConfig, MCMCRefiner
from .microcells import VoxelHash, grow
from .resolution import coarser_for
from .seeding import seeds_from_depth
from .support import SupportProbe


@dataclass
class GrowthConfig:
    voxel_size: float = 0.05
    """Metres: edge of an evidence voxel."""
    seed_stride: int = 4
    """Support-render pixels: one sparse-support seed per stride x stride block."""
    max_seeds_per_frame: int = 1500
    """Bound on the sparse support one frame may add."""
    seed_follows_detail: bool = True
    """Where point supervision is chosen, ``seed_stride`` counts pixels of the updates' scale (lab: growth-seed-detail)."""
    insert_stride: int = 2
    """Support-render pixels: evidence-gated insertion adds one Gaussian per stride x stride block of a ready voxel."""
    max_insert_per_frame: int = 2000
    """Bound on one frame's insertions."""
    min_views: int = 2
    """Distinct views that must find a voxel unexplained before it grows."""
    min_fraction: float = 0.5
    """A view votes for a voxel when at least this share of its samples there are unexplained."""
    init_opacity: float = 0.5
    """Opacity in (0, 1) of inserted Gaussians (3DGS-MCMC's initial value)."""
    footprint: float = 0.5
    """A new Gaussian's scale as a share of its stride x stride pixel block (0.5: neighbours touch)."""
    budget_updates: float = 4.0
    """The map grows only while a source frame still buys this many updates at ``budget_scale`` (0: no budget cap)."""
    budget_scale: float = 0.25
    """Supervision scale that prices the budget cap (0: the current update's scale) (lab: growth-budget-cap)."""
    budget_follows_camera: bool = True
    """On a camera larger than 640x480, ``budget_scale`` times a power of two, as the fidelity floor."""
    budget_min_gaussians: int = 1000
    """The budget cap never goes below this many Gaussians."""
    budget_fill: float = 0.0
    """Under a budget cap, each MCMC densification adds at least this share of the room left."""
    mcmc: MCMCConfig = field(default_factory=MCMCConfig)
    """3DGS-MCMC population refinement: relocation, replacement and densification under the cap."""


class TargetedGrowth(GrowthPolicy):
    """Sparse support for new space + evidence-gated insertion + 3DGS-MCMC refinement, under ``ctx.max_gaussians``."""

    name = "targeted"

    def __init__(self, cfg: GrowthConfig | None = None, probe: SupportProbe | None = None, seed: int = 0):
        self.cfg = cfg or GrowthConfig()
        self.probe = probe or SupportProbe()
        self.voxels = VoxelHash(self.cfg.voxel_size)
        self.votes = torch.zeros(0, dtype=torch.long)
        self.last_view = torch.zeros(0, dtype=torch.long)
        self.mcmc = MCMCRefiner(self.cfg.mcmc, seed=seed)
        self.rng = torch.Generator().manual_seed(seed + 1)
        self.counts = {"seeded": 0, "reseeded": 0, "inserted": 0, "replaced": 0}
        if not 0.0 <= self.cfg.budget_scale <= 1.0:
            raise ValueError(f"growth.budget_scale must lie in [0, 1], got {self.cfg.budget_scale}")
        self.budget = BudgetCap(self.cfg.budget_updates, self.cfg.budget_min_gaussians)
        self.pixels = 0  # supervised pixels that price the budget cap (0: the probe's until an update or frame sets it)

    def attach(self, period_s: float | None, cost=None) -> None:
        self.budget.attach(period_s, cost)

    def cap(self, ctx: MapContext, pixels: int, in_view: int | None = None) -> int:
        """The map-size cap now: ``ctx.max_gaussians`` (memory), lowered by the budget cap when one is set. The
        budget prices an update by the Gaussians in its view, so with ``in_view`` (the Gaussians that reach the
        view at hand) it caps those: the map may hold ``budget cap - in_view`` more, wherever the view leaves room."""
        cap = self.budget.cap(ctx.max_gaussians, pixels)
        if in_view is None:
            return cap
        n = len(ctx.gmap)
        return int(min(ctx.max_gaussians, n - min(int(in_view), n) + cap))

    # ---- per released frame ---------------------------------------------------------------------------------
    def on_frame(self, frame: Frame, admitted: bool, ctx: MapContext) -> int:
        if not admitted:
            return 0  # evidence comes from distinct (admitted) views only; near-duplicates would double count
        sup = self.probe.check(frame, ctx)
        if self.cfg.budget_scale > 0:
            self.pixels = self._budget_pixels(frame.camera)
        cap = self.cap(ctx, self.pixels or sup.camera.pixels, ctx.in_view(sup.camera, frame.T_world_cam))
        vs, us = torch.nonzero(sup.valid, as_tuple=True)
        if vs.numel() == 0:
            return 0
        pts = _world(sup.depth, sup.camera, frame.T_world_cam, vs, us)
        with ctx.timing.sub("growth.voxel_hash"):
            ids, first_seen = self.voxels.lookup(pts)
        n = len(self.voxels)
        self.votes = grow(self.votes, n, 0)
        self.last_view = grow(self.last_view, n, -1)
        bad = (sup.unsupported | sup.misplaced)[vs, us]

        # sparse structural support where space is seen for the first time and nothing renders there
        new_space = first_seen & sup.unsupported[vs, us]
        added = self._insert(sup, frame, vs[new_space], us[new_space], self._seed_stride(sup, frame, ctx),
                             self.cfg.max_seeds_per_frame, ctx, "seeded", cap)

        # evidence: one vote per distinct view for known voxels it finds mostly unexplained; explained loses one
        known = ~first_seen
        ready = torch.zeros(0, dtype=torch.long)
        if bool(known.any()):
            cells, inv = torch.unique(ids[known], return_inverse=True)
            total = torch.zeros(cells.numel()).index_add_(0, inv, torch.ones(inv.numel()))
            unexplained = torch.zeros(cells.numel()).index_add_(0, inv, bad[known].float())
            vote = unexplained / total >= self.cfg.min_fraction
            fresh = self.last_view[cells] != frame.index
            up = cells[vote & fresh]
            down = cells[~vote & fresh]
            self.votes[up] += 1
            self.votes[down] = (self.votes[down] - 1).clamp_min(0)
            self.last_view[cells[fresh]] = frame.index
            ready = cells[self.votes[cells] >= self.cfg.min_views]
        if ready.numel():
            is_ready = torch.zeros(n, dtype=torch.bool)
            is_ready[ready] = True
            sel = known & bad & is_ready[ids]
            added += self._insert(sup, frame, vs[sel], us[sel], self.cfg.insert_stride,
                                  self.cfg.max_insert_per_frame, ctx, "inserted", cap)
            self.votes[ready] = 0  # grown: new evidence is needed before this voxel grows again
        return added

    def reseed(self, frames: list[Frame], ctx: MapContext) -> int:
        """When seeds have just become finer (``ctx.seed_scale`` set: the views were found to agree at full
        resolution), the views admitted before got seeds on the coarser grid: each gets the finer grid's seeds over
        all its valid depth, on top of what it has (the coarse seeds sit between them; relocation reuses those that
        fade). Without it the first views stay on the coarse grid (lab: growth-reseed)."""
        added = 0
        if ctx.seed_scale is None or not self.cfg.seed_follows_detail:
            return added  # seeds on the probe's grid: nothing finer to add
        for frame in frames:
            sup = self.probe.check(frame, ctx)
            stride = self._seed_stride(sup, frame, ctx)
            if stride >= self.cfg.seed_stride:
                continue
            cap = self.cap(ctx, self.pixels or sup.camera.pixels, ctx.in_view(sup.camera, frame.T_world_cam))
            vs, us = torch.nonzero(sup.valid, as_tuple=True)
            added += self._insert(sup, frame, vs, us, stride, self.cfg.max_seeds_per_frame, ctx, "reseeded", cap)
        return added

    def _budget_pixels(self, camera: Camera) -> int:
        """Supervised pixels that price the budget cap: an update at ``budget_scale``, coarser on a camera larger
        than 640x480 (``budget_follows_camera``)."""
        return _pixels_at(camera, coarser_for(self.cfg.budget_scale, camera, self.cfg.budget_follows_camera))

    def _seed_stride(self, sup, frame: Frame, ctx: MapContext) -> int:
        """New-space seeds' stride in probe pixels: ``seed_stride``, or that many pixels of ``ctx.seed_scale`` where
        it is set (``seed_follows_detail``), never coarser."""
        scale = ctx.seed_scale if self.cfg.seed_follows_detail else None
        if scale is None:
            return self.cfg.seed_stride
        probe = sup.camera.width / frame.camera.width
        return max(1, min(self.cfg.seed_stride, round(self.cfg.seed_stride * probe / scale)))

    def _room(self, ctx: MapContext, limit: int, cap: int) -> tuple[int, torch.Tensor, int]:
        """(room to append under ``cap``, dead Gaussians that may be written over, how many may be placed)."""
        room = max(0, cap - len(ctx.gmap))
        dead = torch.zeros(0, dtype=torch.long)
        if room < limit and len(ctx.gmap):
            dead = torch.nonzero(ctx.gmap.opacities.detach().cpu() <= self.cfg.mcmc.min_opacity).squeeze(1)
        return room, dead, min(limit, room + dead.numel())

    def _insert(self, sup, frame: Frame, vs, us, stride: int, limit: int, ctx: MapContext, what: str,
                cap: int) -> int:
        """Gaussians at the given probe pixels on a ``stride`` grid: appended while under ``cap``, else written
        over dead (low-opacity) Gaussians (MCMC-style replacement); never beyond ``cap``."""
        if vs.numel() == 0:
            return 0
        with ctx.timing.sub("growth.insert"):
            return self._seed(sup, frame, vs, us, stride, limit, ctx, what, cap)

    def _seed(self, sup, frame: Frame, vs, us, stride: int, limit: int, ctx: MapContext, what: str, cap: int) -> int:
        mask = torch.zeros_like(sup.valid)
        mask[vs, us] = True
        room, dead, budget = self._room(ctx, limit, cap)
        if budget <= 0:
            return 0
        seeds = seeds_from_depth(sup.color, sup.depth, sup.camera, frame.T_world_cam, mask, stride, budget,
                                 self.rng, self.cfg.footprint)
        return self._place(seeds, room, dead, ctx, what)

    def _place(self, seeds, room: int, dead: torch.Tensor, ctx: MapContext, what: str) -> int:
        """Append ``seeds`` (means, rgbs, scales) while there is room, then write the rest over ``dead``."""
        means, rgbs, scales = seeds
        m = means.shape[0]
        if m == 0:
            return 0
        n_add = min(m, room)
        if n_add:
            ctx.gmap.add(means[:n_add], rgbs[:n_add], scales[:n_add], self.cfg.init_opacity)
        if m > n_add:  # at the cap: replace dead Gaussians (their optimizer moments are reset)
            idx = dead[: m - n_add].to(ctx.gmap.device)
            k = idx.numel()
            tmp = _raw_params(ctx.gmap, means[n_add:n_add + k], rgbs[n_add:n_add + k], scales[n_add:n_add + k],
                              self.cfg.init_opacity)
            ctx.gmap.assign(idx, tmp, anchors=ctx.gmap.anchor_view)
            self.counts["replaced"] += k
            m = n_add + k
        self.counts[what] += m
        return m

    # ---- around every update --------------------------------------------------------------------------------
    def step_terms(self, ctx: MapContext) -> StepTerms:
        """3DGS-MCMC's regularisers and, unless this update ends in a relocation round (whose noise follows the
        relocation), its position noise: both applied by the update's step on the rows in view."""
        m = self.cfg.mcmc
        return StepTerms(m.opacity_reg, m.scale_reg, self.mcmc.step_noise(ctx.gmap), self.mcmc.generator(ctx.device))

    def post_step(self, frame: Frame, out: RenderOutput, depth: torch.Tensor, camera: Camera, ctx: MapContext) -> None:
        self.pixels = self._budget_pixels(frame.camera) if self.cfg.budget_scale > 0 else camera.pixels
        view = ctx.view
        if not self.mcmc.refines_next(ctx.gmap):  # no round: the cap and the rows are not needed
            self.mcmc.post_step(ctx.gmap, len(ctx.gmap))
            return
        cap = self.cap(ctx, self.pixels, None if view is None else len(view))
        fill = 0
        if self.cfg.budget_updates > 0 and self.cfg.budget_fill > 0:
            fill = math.ceil(self.cfg.budget_fill * max(0, cap - len(ctx.gmap)))
        self.mcmc.post_step(ctx.gmap, cap, fill, None if view is None else view.rows)

    def counters(self) -> dict:
        return {**self.counts, **self.mcmc.counts, "evidence_voxels": len(self.voxels)}

    # ---- persistence ----------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        n = len(self.voxels)
        return {"voxels": self.voxels.state_dict(), "votes": self.votes[:n].clone(),
                "last_view": self.last_view[:n].clone(), "mcmc": self.mcmc.state_dict(),
                "rng": self.rng.get_state(), "counts": dict(self.counts)}

    def load_state_dict(self, state: dict) -> None:
        self.voxels.load_state_dict(state["voxels"])
        self.votes, self.last_view = state["votes"].clone(), state["last_view"].clone()
        self.mcmc.load_state_dict(state["mcmc"])
        self.rng.set_state(state["rng"])
        self.counts.update(state.get("counts", {}))


def _pixels_at(camera: Camera, scale: float) -> int:
    """Supervised pixels of an update of ``camera``'s image at ``scale``."""
    return int(camera.scaled(scale).pixels)


def _world(depth: torch.Tensor, camera: Camera, T_world_cam, vs: torch.Tensor, us: torch.Tensor) -> torch.Tensor:
    """World points [M, 3] of pixels (vs, us) of a depth image [h, w] (pixel centres at integers)."""
    return camera.unproject(us, vs, depth[vs, us], T_world_cam)


def _raw_params(gmap, means, rgbs, scales, opacity: float) -> dict[str, torch.Tensor]:
    """Raw parameters of new Gaussians (as :meth:`GaussianMap.add` would store them), for in-place replacement."""
    from ..core.gaussians import rgb_to_sh0

    m, dev = means.shape[0], gmap.device
    quats = torch.zeros(m, 4, device=dev)
    quats[:, 0] = 1.0
    return {"means": means.to(dev), "scales": torch.log(scales.to(dev).clamp_min(1e-6))[:, None].expand(m, 3),
            "quats": quats, "opacities": torch.logit(torch.full((m,), opacity, device=dev)),
            "sh0": rgb_to_sh0(rgbs.to(dev))[:, None, :], "shN": torch.zeros(m, gmap.params["shN"].shape[1], 3, device=dev)}
