"""GaussianMap: the Gaussian parameters and their Adam state, kept aligned on every add, remove and relocation.

Raw parameters are stored (log scales, logit opacities, unnormalised wxyz quaternions, SH coefficients); activated
values are exposed as properties. The parameters and their Adam moments (:class:`.optim.adam.MapAdam`) share one
row layout in capacity buffers: every change of the population (:meth:`GaussianMap.add`, ``remove``, ``assign``)
rewrites the rows of all of them together (the gsplat strategy-ops pattern), without copying the map per insertion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..optim.adam import AdamConfig, MapAdam

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
    """Step size of the means, in metres."""
    scales: float = 1e-2
    """Step size of the log scales."""
    quats: float = 1e-3
    """Step size of the rotations' quaternion components."""
    opacities: float = 5e-2
    """Step size of the opacities' logits."""
    sh0: float = 5e-3
    """Step size of the base colour (SH degree 0)."""
    shN: float = 5e-3 / 20
    """Step size of the view-dependent colour (SH degrees >= 1)."""


PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")
MIN_CAPACITY = 256  # rows a map's buffers hold at least once it has grown


class GaussianMap:
    """N 3D Gaussians with spherical-harmonic colour of degree ``sh_degree`` and their Adam state (``adam``).

    Every parameter and both of its Adam moments live in a buffer of ``capacity`` rows; ``params[name]`` is a
    ``torch.nn.Parameter`` viewing the first N rows of its buffer, and ``adam.exp_avg[name]`` /
    ``adam.exp_avg_sq[name]`` view the first N rows of theirs. :meth:`add` writes the new rows into the slack
    (the buffers grow by half when full, so an insertion costs its own rows, amortised), :meth:`remove` compacts
    in place, keeping the order. The moment rows past N are kept at zero, so an added row starts with fresh
    moments without writing them.
    """

    def __init__(self, sh_degree: int = 0, device: str | torch.device = "cpu", lrs: LearningRates | None = None,
                 adam: AdamConfig | None = None):
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
        self.sh_degree = sh_degree
        self.device = torch.device(device)
        self.lrs = lrs or LearningRates()
        self.adam_config = adam or AdamConfig()
        self.adam = MapAdam({n: getattr(self.lrs, n) for n in PARAM_NAMES}, self.adam_config)
        k = (sh_degree + 1) ** 2 - 1
        empty = {
            "means": torch.zeros(0, 3), "scales": torch.zeros(0, 3), "quats": torch.zeros(0, 4),
            "opacities": torch.zeros(0), "sh0": torch.zeros(0, 1, 3), "shN": torch.zeros(0, k, 3),
        }
        self.params: dict[str, torch.nn.Parameter] = {}  # a plain dict: read several times per update
        self._set_rows({n: v.to(self.device) for n, v in empty.items()})
        self.supervision_focal: float | None = None  # the finest focal length [px] an update supervised it at
        self.rows_epoch = 0  # changes whenever row ids change meaning (removal, reload)
        self.row_index = None  # a spatial index over the rows (render.cell_index), told of every change
        self.anchor_view = -1  # the anchor (a keyframe's frame index, core.anchors) of rows added from now on

    # ---- capacity ----------------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        """Rows the buffers hold (N of them in use)."""
        return self._buffers["means"][0].shape[0]

    def nbytes(self) -> int:
        """Bytes held by the buffers of the parameters and their two Adam moments (the whole capacity)."""
        return sum(t.numel() * t.element_size() for bufs in self._buffers.values() for t in bufs)

    def _set_rows(self, params: dict[str, torch.Tensor]) -> None:
        """New buffers holding exactly ``params`` (raw, [N, ...] each), with zero moments."""
        self._n = params["means"].shape[0]
        self._buffers = {n: (params[n].detach().clone(), torch.zeros_like(params[n]), torch.zeros_like(params[n]))
                         for n in PARAM_NAMES}
        self._anchor_buf = torch.full((self._n,), -1, dtype=torch.int64, device=self.device)
        self._view()

    def _view(self) -> None:
        """Point ``params`` and the Adam moments at the first N rows of their buffers."""
        n = self._n
        self._host = None
        for name, (p, m, v) in self._buffers.items():
            self.params[name] = torch.nn.Parameter(p[:n])
            self.adam.exp_avg[name] = m[:n]
            self.adam.exp_avg_sq[name] = v[:n]

    def reserve(self, rows: int) -> None:
        """Make room for ``rows`` rows in all; a full buffer grows to 1.5x (at least ``MIN_CAPACITY`` rows)."""
        cap = self.capacity
        if rows <= cap:
            return
        cap = max(rows, cap + cap // 2, MIN_CAPACITY)
        n = self._n
        for name, (p, m, v) in self._buffers.items():
            grown = []
            for i, old in enumerate((p, m, v)):  # the moments' new rows zero, the parameters' written on use
                new = (torch.empty if i == 0 else torch.zeros)((cap, *old.shape[1:]), dtype=old.dtype,
                                                              device=old.device)
                new[:n] = old[:n]
                grown.append(new)
            self._buffers[name] = tuple(grown)
        anchors = torch.full((cap,), -1, dtype=torch.int64, device=self.device)
        anchors[:n] = self._anchor_buf[:n]
        self._anchor_buf = anchors
        self._view()

    def host_buffers(self) -> dict:
        """A CPU map's buffers as flat numpy arrays over the whole capacity, by parameter name: (parameter,
        exp_avg, exp_avg_sq), row r at r * its width; rows below N are the map's. Compiled kernels read and write
        the rows in place through them. Kept until the buffers change (growth, removal, reload)."""
        if self._host is None:
            if self.device.type != "cpu":
                raise ValueError(f"host_buffers: the map is on {self.device}, not the CPU")
            self._host = {n: tuple(t.detach().view(-1).numpy() for t in bufs) for n, bufs in self._buffers.items()}
        return self._host

    # ---- activated views -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    @property
    def anchors(self) -> torch.Tensor:  # [N] int64: the keyframe each row moves with (-1: none; core.anchors)
        return self._anchor_buf[: self._n]

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
    @torch.no_grad()
    def add(self, means: torch.Tensor, rgbs: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor | float,
            quats: torch.Tensor | None = None) -> torch.Tensor:
        """Append Gaussians given in activated units (scales in metres [M] or [M, 3], opacity in (0, 1)).

        Returns the indices of the new Gaussians. Their Adam moments start at zero. The existing rows are not
        copied unless the buffers grow."""
        m = means.shape[0]
        dev = self.device
        n0, n1 = self._n, self._n + m
        self.reserve(n1)
        rows = {name: bufs[0][n0:n1] for name, bufs in self._buffers.items()}
        scales = torch.as_tensor(scales, dtype=torch.float32, device=dev)
        if scales.ndim == 1:
            scales = scales[:, None].expand(m, 3)
        # the activations on [M] tensors shaped as always: torch's vector and scalar loops may differ in the last bit
        opac = torch.as_tensor(opacities, dtype=torch.float32, device=dev).expand(m).clamp(1e-4, 1 - 1e-4)
        rows["means"].copy_(means)
        rows["scales"].copy_(torch.log(scales.clamp_min(1e-6)))
        if quats is None:
            rows["quats"].copy_(torch.tensor([1.0, 0.0, 0.0, 0.0], device=dev))
        else:
            rows["quats"].copy_(quats)
        torch.logit(opac, out=rows["opacities"])
        rows["sh0"][:, 0].copy_(rgb_to_sh0(rgbs.to(dev, torch.float32)))
        rows["shN"].zero_()
        self._anchor_buf[n0:n1] = self.anchor_view
        self._n = n1
        self._view()
        return torch.arange(n0, n1, device=dev)

    @torch.no_grad()
    def remove(self, mask: torch.Tensor) -> None:
        """Remove Gaussians where ``mask`` [N] is True, compacting the buffers in place (order kept)."""
        n = self._n
        keep = torch.nonzero(~mask.to(self.device)).squeeze(1)
        k = keep.numel()
        for p, m, v in self._buffers.values():
            for buf in (p, m, v):
                buf[:k] = torch.index_select(buf[:n], 0, keep)
            m[k:n] = 0  # the moment rows past N stay zero
            v[k:n] = 0
        self._anchor_buf[:k] = torch.index_select(self._anchor_buf[:n], 0, keep)
        self._n = k
        self._view()
        self.rows_epoch += 1

    def assign(self, idx: torch.Tensor, values: dict[str, torch.Tensor], reset_state: bool = True,
               anchors: torch.Tensor | int | None = None) -> None:
        """Overwrite raw parameters at ``idx`` (MCMC relocation/replacement), zeroing their Adam moments;
        ``anchors``: the rows' new anchors (the copied rows' for a relocation, ``anchor_view`` for new content;
        None keeps them)."""
        with torch.no_grad():
            if anchors is not None:
                self._anchor_buf[:self._n][idx] = torch.as_tensor(anchors, dtype=torch.int64, device=self.device)
            for name, v in values.items():
                self.params[name][idx] = v.to(self.params[name].dtype)
                if reset_state:
                    self.adam.exp_avg[name][idx] = 0
                    self.adam.exp_avg_sq[name][idx] = 0
        self.touched(idx)

    def touched(self, rows: torch.Tensor | None = None) -> None:
        """Tell the row index that ``rows`` (ids; None: all) changed in place (Adam, position noise, assignment)."""
        if self.row_index is not None:
            self.row_index.mark(rows)

    # ---- optimisation ----------------------------------------------------------------------------------
    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def step(self) -> None:
        """One Adam step on every parameter that received a gradient (:meth:`.optim.adam.MapAdam.step_map`)."""
        self.touched()
        self.adam.step_map(self.params, {n: p.grad for n, p in self.params.items()})

    def check_aligned(self) -> None:
        """Raise if a parameter or its Adam state disagrees with N or has left its buffer (an invariant the tests
        hold us to)."""
        n = len(self)
        for name in PARAM_NAMES:
            p = self.params[name]
            if p.shape[0] != n:
                raise AssertionError(f"{name} has {p.shape[0]} rows, map has {n}")
            for what, t, buf in zip(("parameter", "exp_avg", "exp_avg_sq"),
                                    (p, self.adam.exp_avg[name], self.adam.exp_avg_sq[name]), self._buffers[name]):
                if t.shape != p.shape:
                    raise AssertionError(f"{name} {what} has shape {tuple(t.shape)}, parameter {tuple(p.shape)}")
                if t.data_ptr() != buf.data_ptr() or buf.shape[0] < n:
                    raise AssertionError(f"{name} {what} is not the first {n} rows of its buffer")

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
            # copies: on the CPU .cpu() shares memory with the live tensors, which the next update changes in place
            # (a state taken, then mapped on, would change under its holder)
            "params": {n: p.detach().cpu().clone() for n, p in self.params.items()},
            "adam": self.adam.state_dict(),
            "anchors": self.anchors.cpu().clone(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s map; without ``adam`` (a PLY) the moments start at zero and the step
        counts at 0."""
        self.rows_epoch += 1
        self.sh_degree = int(state["sh_degree"])
        f = state.get("supervision_focal")  # absent in maps written before it was kept
        self.supervision_focal = None if f is None else float(f)
        self.adam = MapAdam({n: getattr(self.lrs, n) for n in PARAM_NAMES}, self.adam_config)
        self._set_rows({n: state["params"][n].to(self.device) for n in PARAM_NAMES})
        if "adam" in state:
            self.adam.load_state_dict(state["adam"])
        if state.get("anchors") is not None:  # absent in maps written before anchors (and in PLYs): none
            self._anchor_buf.copy_(torch.as_tensor(state["anchors"], dtype=torch.int64))

    def render_args(self) -> tuple:
        """(means, quats, scales, opacities, colors) in activated units, as every renderer takes them.

        colors: [N, 3] RGB at sh_degree 0, else the SH coefficients [N, K, 3], which every renderer evaluates for
        the pose it renders (gsplat in its own kernel): the renderer's pose fixes the viewing directions.
        """
        colors = self.colors() if self.sh_degree == 0 else self.sh
        return self.means, self.quats, self.scales, self.opacities, colors
