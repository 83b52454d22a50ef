"""GaussianMap: the Gaussian parameters and their Adam state, kept aligned on every add, remove and relocation.

Raw parameters are stored (log scales, logit opacities, unnormalised wxyz quaternions, SH coefficients); activated
values are exposed as properties. Every change of the population goes through :meth:`_resize`, the one place that
rewrites parameters and optimizer moments together (the gsplat strategy-ops pattern).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch

SH_C0 = 0.28209479177387814  # Y_0^0
EPS2D = 0.3  # px^2: 3DGS's screen-space low-pass at the supervised resolution (every renderer's default)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * SH_C0 + 0.5


@dataclass
class LearningRates:
    """Adam step sizes per parameter (metres for means; log/logit/SH units otherwise)."""

    means: float = 5e-4
    scales: float = 1e-2  # 2x 3DGS's: short online schedules (7-Scenes 200 frames: +0.15 dB real time, +0.38 at 0.1x)
    quats: float = 1e-3
    opacities: float = 5e-2
    sh0: float = 5e-3
    shN: float = 5e-3 / 20


PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


@dataclass
class AdamConfig:
    """Adam's settings and the per-Gaussian (row) schedule of :meth:`GaussianMap.step`.

    Torch's Adam corrects the bias of its moments with one step count per tensor, so a Gaussian inserted (or
    relocated, its moments zeroed) after thousands of updates starts with an uncorrected, 3-6x larger step that
    takes hundreds of updates to settle. ``row_bias_correction`` counts the steps of every row since its moments
    were zeroed and corrects each row with its own count (exact Adam for every Gaussian from its birth).
    ``means_decay_to`` < 1 decays the position step size of each Gaussian exponentially with the number of updates
    that reached it (3DGS decays it with the global iteration; an online map has no fixed length): ``lr_means *
    means_decay_to ** min(seen / means_decay_updates, 1)``. ``warmup_updates`` > 0 ramps every step size of a new
    Gaussian linearly over its first updates that reach it. All off by default (= torch's Adam).
    """

    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-15
    row_bias_correction: bool = False
    means_decay_to: float = 1.0
    means_decay_updates: int = 500
    warmup_updates: int = 0

    def rows(self) -> bool:
        """Whether :meth:`GaussianMap.step` needs per-row step counts."""
        return self.row_bias_correction or self.means_decay_to != 1.0 or self.warmup_updates > 0


ROW_STATE = ("row_step", "row_seen")  # per-Gaussian counters in the Adam state (:mod:`.row_adam`)


def _check_adam(a: AdamConfig) -> None:
    if not (0 <= a.beta1 < 1 and 0 <= a.beta2 < 1 and a.eps > 0):
        raise ValueError(f"optim.adam: betas must lie in [0, 1) and eps > 0, got beta1={a.beta1}, beta2={a.beta2}, "
                         f"eps={a.eps}")
    if not 0 < a.means_decay_to <= 1 or a.means_decay_updates < 1 or a.warmup_updates < 0:
        raise ValueError(f"optim.adam: means_decay_to must lie in (0, 1], means_decay_updates >= 1 and "
                         f"warmup_updates >= 0, got {a.means_decay_to}, {a.means_decay_updates}, {a.warmup_updates}")


class GaussianMap:
    """N 3D Gaussians with spherical-harmonic colour of degree ``sh_degree`` and one Adam per parameter."""

    def __init__(self, sh_degree: int = 0, device: str | torch.device = "cpu", lrs: LearningRates | None = None,
                 adam: AdamConfig | None = None):
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
        self.sh_degree = sh_degree
        self.device = torch.device(device)
        self.lrs = lrs or LearningRates()
        self.adam = adam or AdamConfig()
        _check_adam(self.adam)
        k = (sh_degree + 1) ** 2 - 1
        empty = {
            "means": torch.zeros(0, 3), "scales": torch.zeros(0, 3), "quats": torch.zeros(0, 4),
            "opacities": torch.zeros(0), "sh0": torch.zeros(0, 1, 3), "shN": torch.zeros(0, k, 3),
        }
        self.params = torch.nn.ParameterDict({n: torch.nn.Parameter(v.to(self.device)) for n, v in empty.items()})
        self.optimizers = {n: self._make_optimizer(n) for n in PARAM_NAMES}
        self.supervision_focal: float | None = None  # the finest focal length [px] an update supervised it at
        self.rows_epoch = 0  # changes whenever row ids change meaning (removal, reload)
        self.row_index = None  # a spatial index over the rows (render.cell_index), told of every change

    def _make_optimizer(self, name: str) -> torch.optim.Adam:
        a = self.adam
        return torch.optim.Adam([self.params[name]], lr=getattr(self.lrs, name), betas=(a.beta1, a.beta2), eps=a.eps)

    # ---- activated views -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> torch.Tensor:  # [N, 3] metres
        return self.params["means"]

    @property
    def scales(self) -> torch.Tensor:  # [N, 3] metres
        return torch.exp(self.params["scales"])

    @property
    def quats(self) -> torch.Tensor:  # [N, 4] wxyz, unnormalised
        return self.params["quats"]

    @property
    def opacities(self) -> torch.Tensor:  # [N] in (0, 1)
        return torch.sigmoid(self.params["opacities"])

    @property
    def sh(self) -> torch.Tensor:  # [N, (sh_degree + 1)^2, 3] all SH coefficients, DC first
        return torch.cat([self.params["sh0"], self.params["shN"]], 1)

    def colors(self, cam_center: torch.Tensor | None = None) -> torch.Tensor:
        """[N, 3] RGB seen from ``cam_center`` [3] (world metres); without one, or at sh_degree 0, the DC colour."""
        if self.sh_degree == 0 or cam_center is None:
            return torch.clamp_min(sh0_to_rgb(self.params["sh0"][:, 0]), 0.0)
        from ..render.sh import sh_eval

        dirs = self.means - torch.as_tensor(cam_center, dtype=self.means.dtype, device=self.device)[None]
        return sh_eval(self.sh, dirs, self.sh_degree)

    # ---- population changes ----------------------------------------------------------------------------
    def add(self, means: torch.Tensor, rgbs: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor | float,
            quats: torch.Tensor | None = None) -> torch.Tensor:
        """Append Gaussians given in activated units (scales in metres [M] or [M, 3], opacity in (0, 1)).

        Returns the indices of the new Gaussians. Their Adam moments start at zero.
        """
        m = means.shape[0]
        dev = self.device
        scales = torch.as_tensor(scales, dtype=torch.float32, device=dev)
        if scales.ndim == 1:
            scales = scales[:, None].expand(m, 3)
        opac = torch.as_tensor(opacities, dtype=torch.float32, device=dev).expand(m).clamp(1e-4, 1 - 1e-4)
        if quats is None:
            quats = torch.zeros(m, 4, device=dev)
            quats[:, 0] = 1.0
        new = {
            "means": means.to(dev, torch.float32),
            "scales": torch.log(scales.clamp_min(1e-6)),
            "quats": quats.to(dev, torch.float32),
            "opacities": torch.logit(opac),
            "sh0": rgb_to_sh0(rgbs.to(dev, torch.float32))[:, None, :],
            "shN": torch.zeros(m, self.params["shN"].shape[1], 3, device=dev),
        }
        n0 = len(self)
        self._resize(lambda name, p: torch.cat([p, new[name].to(p.dtype)], 0),
                     lambda name, s: torch.cat([s, torch.zeros((m, *s.shape[1:]), dtype=s.dtype, device=s.device)], 0))
        return torch.arange(n0, n0 + m, device=dev)

    def remove(self, mask: torch.Tensor) -> None:
        """Remove Gaussians where ``mask`` [N] is True."""
        keep = ~mask.to(self.device)
        self._resize(lambda name, p: p[keep], lambda name, s: s[keep])
        self.rows_epoch += 1

    def assign(self, idx: torch.Tensor, values: dict[str, torch.Tensor], reset_state: bool = True) -> None:
        """Overwrite raw parameters at ``idx`` (MCMC relocation/replacement), zeroing their Adam moments."""
        with torch.no_grad():
            for name, v in values.items():
                self.params[name][idx] = v.to(self.params[name].dtype)
        self.touched(idx)
        if reset_state:
            for name in values:
                for s in self.optimizers[name].state.get(self.params[name], {}).values():
                    if isinstance(s, torch.Tensor) and s.ndim > 0 and s.shape[0] == len(self):
                        s[idx] = 0

    def touched(self, rows: torch.Tensor | None = None) -> None:
        """Tell the row index that ``rows`` (ids; None: all) changed in place (Adam, position noise, assignment)."""
        if self.row_index is not None:
            self.row_index.mark(rows)

    def _resize(self, param_fn, state_fn) -> None:
        """Rewrite every parameter with ``param_fn`` and its per-Gaussian Adam moments with ``state_fn``."""
        for name in PARAM_NAMES:
            opt = self.optimizers[name]
            old = self.params[name]
            new = torch.nn.Parameter(param_fn(name, old.detach()))
            state = opt.state.pop(old, None)
            if state is not None:
                state = {k: (state_fn(name, v) if isinstance(v, torch.Tensor) and v.ndim > 0 else v)
                         for k, v in state.items()}
                opt.state[new] = state
            opt.param_groups[0]["params"] = [new]
            self.params[name] = new

    # ---- optimisation ----------------------------------------------------------------------------------
    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def step(self) -> None:
        """One Adam step on every parameter that received a gradient (on the CPU all in one compiled
        pass, :func:`._update_kernels.adam_step`: torch's per-optimizer overhead was most of the cost)."""
        from ..optim import update_kernels as uk

        self.touched()
        if self.adam.rows():
            from ..optim.row_adam import row_adam_step

            row_adam_step(self)
            return
        fused = []
        for name, opt in self.optimizers.items():
            if self.params[name].grad is not None:
                if self.device.type == "cpu" and uk.fits(opt):
                    fused.append(opt)
                else:
                    opt.step()
        uk.adam_step(fused)

    def check_aligned(self) -> None:
        """Raise if a parameter or its Adam state disagrees with N (an invariant the tests hold us to)."""
        n = len(self)
        for name in PARAM_NAMES:
            p = self.params[name]
            if p.shape[0] != n:
                raise AssertionError(f"{name} has {p.shape[0]} rows, map has {n}")
            if self.optimizers[name].param_groups[0]["params"][0] is not p:
                raise AssertionError(f"optimizer of {name} does not hold the current parameter")
            for k, s in self.optimizers[name].state.get(p, {}).items():
                if k in ROW_STATE and isinstance(s, torch.Tensor) and s.shape != p.shape[:1]:
                    raise AssertionError(f"optimizer state {name}.{k} has shape {tuple(s.shape)}, map has {n} rows")
                elif k not in ROW_STATE and isinstance(s, torch.Tensor) and s.ndim > 0 and s.shape != p.shape:
                    raise AssertionError(f"optimizer state {name}.{k} has shape {tuple(s.shape)}, parameter {tuple(p.shape)}")

    # ---- the resolution it was fitted at --------------------------------------------------------------
    def note_supervision(self, camera) -> None:
        """Record that an update supervised the map through ``camera`` (its focal length sets :meth:`low_pass`)."""
        f = math.sqrt(camera.fx * camera.fy)
        self.supervision_focal = f if self.supervision_focal is None else max(self.supervision_focal, f)

    def low_pass(self, camera) -> float:
        """The screen-space low-pass [px^2] to draw this map with through ``camera``: 3DGS's 0.3 px^2 at the
        resolution the map was supervised at, growing with the square of the focal-length ratio where ``camera``
        samples finer (0.3 * 16 = 4.8 px^2 for a map fitted at 1/4 scale and drawn at full size), so every
        Gaussian keeps the screen footprint it had in the supervised images instead of shrinking into gaps and
        speckle (the train-coarse / render-fine case of Mip-Splatting, Yu et al. 2024). Never below 0.3."""
        if self.supervision_focal is None:
            return EPS2D
        return EPS2D * max(1.0, camera.fx * camera.fy / (self.supervision_focal * self.supervision_focal))

    # ---- persistence -----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "sh_degree": self.sh_degree,
            "supervision_focal": self.supervision_focal,
            # copies: on the CPU .cpu() and Adam's state_dict() share memory with the live tensors, which the next
            # update changes in place (a state taken, then mapped on, would change under its holder)
            "params": {n: p.detach().cpu().clone() for n, p in self.params.items()},
            "optimizers": {n: copy.deepcopy(o.state_dict()) for n, o in self.optimizers.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        self.rows_epoch += 1
        self.sh_degree = int(state["sh_degree"])
        f = state.get("supervision_focal")  # absent in maps written before it was kept
        self.supervision_focal = None if f is None else float(f)
        for n in PARAM_NAMES:
            self.params[n] = torch.nn.Parameter(state["params"][n].to(self.device))
            self.optimizers[n] = self._make_optimizer(n)
            if "optimizers" in state:
                self.optimizers[n].load_state_dict(state["optimizers"][n])

    def render_args(self) -> tuple:
        """(means, quats, scales, opacities, colors) in activated units, as every renderer takes them.

        colors: [N, 3] RGB at sh_degree 0, else the SH coefficients [N, K, 3], which every renderer evaluates for
        the pose it renders (gsplat in its own kernel): the renderer's pose fixes the viewing directions.
        """
        colors = self.colors() if self.sh_degree == 0 else self.sh
        return self.means, self.quats, self.scales, self.opacities, colors
