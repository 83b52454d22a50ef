"""3DGS-MCMC population refinement (Kheradmand et al. 2024), in torch so that it runs on any device.

The paper uses it as the population-update mechanism of Targeted Geometry Growth: dead (low-opacity) Gaussians are
relocated onto live ones sampled in proportion to opacity, new Gaussians are added the same way up to the cap, and
opacity/scale regularisers plus opacity-gated position noise keep the population exploring. gsplat's CUDA relocation
kernel is replaced by the closed form: n copies of a Gaussian (opacity o, scale s) get

    o_new = 1 - (1 - o)^(1/n),   s_new = s * o / D,   D = sum_{j=1..n} C(n, j) (-1)^(j-1) o_new^j / sqrt(j),

so that n stacked copies composite to the original opacity (1 - (1 - o_new)^n = o) and the same footprint mass.
D is an alternating sum that cancels badly for large n: it is evaluated in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..core.gaussians import GaussianMap, sh0_to_rgb
from ..render.projection import quat_to_rotmat


@dataclass
class MCMCConfig:
    refine_start: int = 100
    """Updates before the first relocation/densification round."""
    refine_every: int = 100
    """Updates between relocation/densification rounds."""
    min_opacity: float = 0.005
    """A Gaussian below this opacity is dead and relocated onto a live one."""
    growth_rate: float = 0.05
    """Each round adds this share of the map's Gaussians, up to the cap."""
    n_max: int = 51
    """Copies per source Gaussian are clamped to this (the closed-form relocation's table size)."""
    noise_lr: float = 5e5
    """Position noise = the means' learning rate x this x covariance-shaped noise, gated by opacity."""
    opacity_reg: float = 0.01
    """Loss += this x the mean opacity (drives unneeded Gaussians towards relocation)."""
    scale_reg: float = 0.01
    """Loss += this x the mean scale in metres."""


def relocation_params(opacities: torch.Tensor, scales: torch.Tensor, ratios: torch.Tensor,
                      n_max: int = 51) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form opacity [M] and scales [M, 3] of each of ``ratios`` [M] copies of a Gaussian.

    opacities [M] in (0, 1), scales [M, 3] metres (activated). Computed in float64, returned in the input dtype.
    """
    n = ratios.to(torch.float64).clamp(1, n_max)  # [M]
    o = opacities.to(torch.float64).clamp(1e-12, 1 - 1e-12)
    o_new = 1.0 - torch.pow(1.0 - o, 1.0 / n)  # [M]
    j = torch.arange(1, n_max + 1, dtype=torch.float64, device=o.device)  # [J]
    log_binom = torch.lgamma(n[:, None] + 1) - torch.lgamma(j[None] + 1) - torch.lgamma((n[:, None] - j[None]).clamp_min(0) + 1)
    binom = torch.where(j[None] <= n[:, None], torch.exp(log_binom).round(), torch.zeros_like(log_binom))  # C(n, j)
    sign = torch.where(j % 2 == 1, 1.0, -1.0).to(torch.float64)  # (-1)^(j-1)
    terms = binom * sign[None] * torch.pow(o_new[:, None], j[None]) / torch.sqrt(j[None])
    denom = terms.sum(1)
    new_scales = scales.to(torch.float64) * (o / denom)[:, None]
    return o_new.to(opacities.dtype), new_scales.to(scales.dtype)


def _sample(weights: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
    """n indices drawn with replacement in proportion to ``weights``, on their device (``generator`` lives there)."""
    w = weights.detach().double()
    w = torch.where(torch.isfinite(w) & (w > 0), w, torch.zeros_like(w))
    w = torch.where(w.sum() > 0, w, torch.ones_like(w))  # all dead or broken: uniform (decided on the device)
    return torch.multinomial(w, n, replacement=True, generator=generator)


def _split(gmap: GaussianMap, sources: torch.Tensor, min_opacity: float, n_max: int) -> None:
    """Give every sampled source the closed-form opacity/scale of its (copies + 1) share, moments reset."""
    counts = torch.bincount(sources, minlength=len(gmap))
    ratios = counts[sources] + 1
    o_new, s_new = relocation_params(gmap.opacities.detach()[sources], gmap.scales.detach()[sources], ratios, n_max)
    o_new = o_new.clamp(min_opacity, 1.0 - torch.finfo(torch.float32).eps)
    gmap.assign(sources, {"opacities": torch.logit(o_new), "scales": torch.log(s_new)})


def relocate(gmap: GaussianMap, dead: torch.Tensor, generator: torch.Generator | None = None,
             min_opacity: float = 0.005, n_max: int = 51, rows: torch.Tensor | None = None) -> int:
    """Move the Gaussians where ``dead`` [N] is True onto live ones sampled by opacity; returns how many moved.

    Source and copies share the closed-form opacity and scale; the Adam moments of both are reset. ``rows``
    (ids [M]): only those rows are candidates, dead or alive (a culled update's view); ``dead`` is then [M].
    """
    if rows is None:
        dead_idx = torch.nonzero(dead).squeeze(1)
        alive_idx = torch.nonzero(~dead).squeeze(1)
    else:
        dead_idx, alive_idx = rows[dead], rows[~dead]
    if dead_idx.numel() == 0 or alive_idx.numel() == 0:
        return 0
    sources = alive_idx[_sample(gmap.opacities.detach()[alive_idx], dead_idx.numel(), generator)]
    _split(gmap, sources, min_opacity, n_max)
    gmap.assign(dead_idx, {name: p.detach()[sources] for name, p in gmap.params.items()},
                anchors=gmap.anchors[sources])
    return int(dead_idx.numel())


def sample_add(gmap: GaussianMap, n: int, cap: int, generator: torch.Generator | None = None,
               min_opacity: float = 0.005, n_max: int = 51, rows: torch.Tensor | None = None) -> int:
    """Append up to ``n`` copies of live Gaussians sampled by opacity, never exceeding ``cap``; returns the count.
    ``rows`` (ids [M]): the sources are drawn among those rows only."""
    n = min(int(n), cap - len(gmap))
    if n <= 0 or len(gmap) == 0 or (rows is not None and rows.numel() == 0):
        return 0
    if rows is None:
        sources = _sample(gmap.opacities.detach(), n, generator)
    else:
        sources = rows[_sample(torch.sigmoid(gmap.params["opacities"].detach()[rows]), n, generator)]
    _split(gmap, sources, min_opacity, n_max)
    raw = {name: p.detach()[sources].clone() for name, p in gmap.params.items()}
    idx = gmap.add(raw["means"], sh0_to_rgb(raw["sh0"][:, 0]), torch.exp(raw["scales"]),
                   torch.sigmoid(raw["opacities"]), raw["quats"])
    gmap.assign(idx, raw, anchors=gmap.anchors[sources])  # exact raw copies (including higher SH bands)
    return n


@torch.no_grad()
def inject_noise(gmap: GaussianMap, scaler: float, generator: torch.Generator | None = None,
                 rows: torch.Tensor | None = None) -> None:
    """MCMC's exploration noise: covariance-shaped, gated to (nearly) transparent Gaussians
    (sigmoid(100 * ((1 - o) - 0.995)) as in the paper's reference code), scaled by ``scaler`` = lr * noise_lr.
    ``rows`` (ids [M]): only those rows move (one normal triple drawn per row); the others stay untouched."""
    if len(gmap) == 0:
        return
    if rows is not None:
        _noise_at(gmap, scaler, generator, rows)
        return
    gmap.touched()
    if gmap.device.type == "cpu" and gmap.means.dtype == torch.float32:
        from ..optim.update_kernels import mcmc_noise

        z = torch.randn(len(gmap), 3, generator=generator)
        mcmc_noise(gmap.params["means"], gmap.quats, gmap.scales, gmap.opacities, z, scaler)
        return
    o = gmap.opacities
    gate = torch.sigmoid(100.0 * ((1.0 - o) - 0.995))  # [N]
    R = quat_to_rotmat(gmap.quats)
    M = R * gmap.scales[:, None, :]
    cov = M @ M.transpose(1, 2)  # [N, 3, 3]
    z = torch.randn(len(gmap), 3, generator=generator, device=o.device)  # generator on the map's device
    noise = torch.einsum("nij,nj->ni", cov, z) * (gate * scaler)[:, None]
    gmap.params["means"].add_(noise)


def _noise_at(gmap: GaussianMap, scaler: float, generator, rows: torch.Tensor) -> None:
    """:func:`inject_noise` on ``rows`` [M] only: the rows are gathered, moved and written back."""
    if rows.numel() == 0:
        return
    p = gmap.params
    if gmap.device.type == "cpu" and all(p[n].dtype == torch.float32 and p[n].is_contiguous()
                                         for n in ("means", "quats", "scales", "opacities")):
        from ..optim.update_kernels import mcmc_noise_rows

        z = torch.randn(rows.numel(), 3, generator=generator)
        mcmc_noise_rows(p, rows, z, scaler)  # in place, the rows read where they lie
        gmap.touched(rows)
        return
    means = p["means"].detach()[rows]
    quats, scales = p["quats"].detach()[rows], torch.exp(p["scales"].detach()[rows])
    o = torch.sigmoid(p["opacities"].detach()[rows])
    z = torch.randn(rows.numel(), 3, generator=generator, device=o.device)
    if gmap.device.type == "cpu" and means.dtype == torch.float32:
        from ..optim.update_kernels import mcmc_noise

        mcmc_noise(means, quats, scales, o, z, scaler)
    else:
        gate = torch.sigmoid(100.0 * ((1.0 - o) - 0.995))
        M = quat_to_rotmat(quats) * scales[:, None, :]
        means += torch.einsum("nij,nj->ni", M @ M.transpose(1, 2), z) * (gate * scaler)[:, None]
    p["means"].data[rows] = means
    gmap.touched(rows)


class MCMCRefiner:
    """The 3DGS-MCMC hooks: regularisers before backward, relocation/densification/noise after the step.

    Its random numbers (position noise every update, sampling every refinement round) come from one generator on
    the map's device, so an update builds no tensor on the host and copies none over. On the CPU that generator is
    the seeded CPU generator of before (results unchanged); on CUDA it is created at the first step, seeded with
    ``seed``, and checkpointed with its device.
    """

    def __init__(self, cfg: MCMCConfig | None = None, seed: int = 0):
        self.cfg = cfg or MCMCConfig()
        self.seed = seed
        self.rng = torch.Generator().manual_seed(seed)
        self._saved_rng: tuple[torch.device, torch.Tensor] | None = None  # a checkpointed non-CPU generator state
        self.steps = 0
        self.counts = {"relocated": 0, "added": 0}

    def generator(self, device: torch.device) -> torch.Generator:
        """The refiner's generator, moved to ``device`` on first use there (restored from a checkpoint of the same
        device type, else seeded with ``seed``)."""
        if device == self.rng.device:  # the common case: already there
            return self.rng
        device = torch.device(device)
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        if self.rng.device != device:
            rng = torch.Generator(device=device)
            saved = self._saved_rng
            if saved is not None and saved[0].type == device.type:
                rng.set_state(saved[1])
            else:
                rng.manual_seed(self.seed)
            self.rng, self._saved_rng = rng, None
        return self.rng

    def regulariser(self, gmap: GaussianMap) -> torch.Tensor | None:
        if len(gmap) == 0 or (self.cfg.opacity_reg <= 0 and self.cfg.scale_reg <= 0):
            return None
        return self.cfg.opacity_reg * gmap.opacities.mean() + self.cfg.scale_reg * gmap.scales.mean()

    def refines_next(self, gmap: GaussianMap) -> bool:
        """Whether the next :meth:`post_step` is a relocation/densification round."""
        c, k = self.cfg, self.steps + 1
        return k >= c.refine_start and k % c.refine_every == 0 and len(gmap) > 0

    def step_noise(self, gmap: GaussianMap) -> float:
        """The position noise's scale for the update's own step to apply (``lr_means * noise_lr``), or 0 when the
        next :meth:`post_step` relocates first and adds the noise itself after the relocation."""
        if self.cfg.noise_lr <= 0 or self.refines_next(gmap):
            return 0.0
        return gmap.lrs.means * self.cfg.noise_lr

    def post_step(self, gmap: GaussianMap, cap: int, min_add: int = 0, rows: torch.Tensor | None = None) -> None:
        """Relocation and densification every ``refine_every`` updates (densification adds ``growth_rate`` of the
        map, at least ``min_add``, never beyond ``cap``), then the position noise, which every other update's step
        applied already (:meth:`step_noise`). ``rows`` (ids [M], a culled update's view): all of it acts on those
        rows only (relocation among them, copies of them, noise on them; densification adds ``growth_rate`` of M),
        so the rows out of view stay untouched."""
        c = self.cfg
        rng = self.generator(gmap.device)
        refine = self.refines_next(gmap)
        self.steps += 1
        if not refine:
            return
        if rows is None:
            dead = gmap.opacities.detach() <= c.min_opacity
        else:
            dead = torch.sigmoid(gmap.params["opacities"].detach()[rows]) <= c.min_opacity
        self.counts["relocated"] += relocate(gmap, dead, rng, c.min_opacity, c.n_max, rows)
        n_add = max(math.ceil(c.growth_rate * (len(gmap) if rows is None else rows.numel())), int(min_add))
        self.counts["added"] += sample_add(gmap, n_add, cap, rng, c.min_opacity, c.n_max, rows)
        if c.noise_lr > 0:
            inject_noise(gmap, gmap.lrs.means * c.noise_lr, rng, rows)

    def state_dict(self) -> dict:
        return {"rng": self.rng.get_state(), "rng_device": str(self.rng.device), "steps": self.steps,
                "counts": dict(self.counts)}

    def load_state_dict(self, state: dict) -> None:
        device = torch.device(state.get("rng_device", "cpu"))
        if device.type == "cpu":
            self.rng = torch.Generator()
            self.rng.set_state(state["rng"])
        else:  # put on its device at the next step (that device may not exist while loading)
            self.rng = torch.Generator().manual_seed(self.seed)
            self._saved_rng = (device, state["rng"])
        self.steps = int(state["steps"])
        self.counts.update(state.get("counts", {}))
