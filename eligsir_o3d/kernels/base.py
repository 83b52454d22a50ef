"""The contract of a kernel set: the device work of one mapping update, in three stages, behind one object.

An update (``Reconstructor._update``) is: **select** the rows of the map that can reach the view and gather them
as leaves; the renderer draws them; **backward**: the supervision loss, its error map and its gradient, carried
back through the renderer into the leaves; **step**: the activations' chain rule, the regulariser, Adam on those
rows (the tensor's step count, torch's formula) and 3DGS-MCMC's position noise, written into the map's rows in
place. Rows out of view are neither read nor written. A :class:`KernelSet` implements the three stages for one kind
of map; :func:`eligsir_o3d.kernels.get_kernels` chooses it once per map.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, PARAM_NAMES, sh0_to_rgb


@dataclass
class StepTerms:
    """What the growth policy adds to an update's step: the 3DGS-MCMC regularisers' weights
    (``opacity_reg * mean(opacity) + scale_reg * mean(scale)`` over the whole map) and the position noise's scale
    (metres per unit of the covariance-shaped normal draw; 0: no noise in this step) with the generator it draws
    from."""

    opacity_reg: float = 0.0
    scale_reg: float = 0.0
    noise_scaler: float = 0.0
    generator: torch.Generator | None = None


class RowView:
    """The rows ``idx`` of ``gmap`` that one update supervises, with their parameters as leaves that require grad.

    ``activated``: the leaves hold activated values (scales in metres, opacities in (0, 1), colours or SH), else raw
    parameters (log scales, logits, sh0/shN) that :meth:`render_args` activates with autograd. A fused set's view
    has a fixed capacity: ``idx`` [C] holds the rows in its first ``count`` entries, ``count`` stays on the device,
    and its host copy (``count_host``, filled by a non-blocking copy) is read only after the render, whose own
    synchronisation has completed it."""

    def __init__(self, gmap, idx: torch.Tensor, leaves: dict, activated: bool, count: torch.Tensor | None = None,
                 count_host: np.ndarray | None = None):
        self.gmap, self.idx, self.leaves, self.activated = gmap, idx, leaves, activated
        self.n_map = len(gmap)
        self.count, self.count_host = count, count_host

    @property
    def capacity(self) -> int:
        return int(self.idx.shape[0])

    def hits(self) -> int:
        """The number of rows that passed the view test (may exceed :attr:`capacity` in a fused view)."""
        return self.capacity if self.count_host is None else int(self.count_host[0])

    def __len__(self) -> int:
        return min(self.hits(), self.capacity)

    def overflowed(self) -> bool:
        """Whether more rows passed the test than the view holds (a fused view then is re-selected larger)."""
        return self.hits() > self.capacity

    @property
    def rows(self) -> torch.Tensor:
        """The ids [M] of the rows in the view (without a fused view's padding)."""
        return self.idx if self.count_host is None else self.idx[:len(self)]

    def render_args(self) -> tuple:
        """(means, quats, scales, opacities, colors) in activated units, as every renderer takes them."""
        lv = self.leaves
        if self.activated:
            return lv["means"], lv["quats"], lv["scales"], lv["opacities"], lv["colors"]
        if self.gmap.sh_degree == 0:
            colors = torch.clamp_min(sh0_to_rgb(lv["sh0"][:, 0]), 0.0)
        else:
            colors = torch.cat([lv["sh0"], lv["shN"]], 1)
        return lv["means"], lv["quats"], torch.exp(lv["scales"]), torch.sigmoid(lv["opacities"]), colors


def adam_scalars(gmap, name: str) -> tuple:
    """Count one more Adam step of parameter ``name`` and return its host scalars (a, b, beta1, beta2, eps):
    a = -lr / (1 - beta1^k), b = sqrt(1 - beta2^k) with k its step count (torch's Adam counts one per tensor)."""
    a, b = gmap.adam.bias(name)
    return a, b, gmap.adam.beta1, gmap.adam.beta2, gmap.adam.eps


def adam_factors(gmap, name: str) -> tuple:
    """:func:`adam_scalars` as the compiled kernels take them: (a, b, 1 - beta1, beta2, 1 - beta2, eps), the
    complements in float64."""
    a, b, b1, b2, eps = adam_scalars(gmap, name)
    return (a, b, 1.0 - b1, b2, 1.0 - b2, eps)


def moments(gmap, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Adam's (exp_avg, exp_avg_sq) of parameter ``name``, the parameter's shape."""
    return gmap.adam.exp_avg[name], gmap.adam.exp_avg_sq[name]


class KernelSet(ABC):
    """The three stages of an update for one kind of map (see the module docstring)."""

    name = "abstract"
    # the views' fold of a training render's error into their microcells, fused: the arguments of
    # eligsir_o3d.scheduling.cell_feedback.fold_torch; None: that function (torch operators on the map's device)
    fold_cells = None

    @abstractmethod
    def select(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D, *, cull: bool = True,
               grad: bool = True, capacity: int = 0) -> RowView:
        """The rows that can reach ``camera``'s image at ``T_world_cam`` (all rows without ``cull``), gathered as
        leaves (requiring grad with ``grad``); ``capacity``: at least this many rows' room in a fused view."""

    def draw(self, renderer, view: RowView, camera: Camera, T_world_cam, background=None, low_pass: float = EPS2D):
        """``renderer``'s training render of the view's rows (its leaves, as :meth:`RowView.render_args` gives
        them), for :meth:`backward` to differentiate."""
        return renderer.render(*view.render_args(), camera, T_world_cam, background, low_pass=low_pass)

    @abstractmethod
    def backward(self, out, color: torch.Tensor, depth: torch.Tensor, loss_cfg, view: RowView,
                 terms: StepTerms) -> torch.Tensor:
        """The supervision loss of render ``out`` against ``color``/``depth``, back-propagated into the view's
        leaves; returns the detached per-pixel photometric error [h, w] that view scheduling reads."""

    @abstractmethod
    def step(self, gmap, view: RowView, terms: StepTerms) -> None:
        """Chain rule, regulariser, Adam and (``terms.noise_scaler`` > 0) the position noise on the view's rows."""

    @abstractmethod
    def noise(self, gmap, rows: torch.Tensor | None, scaler: float, generator: torch.Generator | None) -> None:
        """MCMC's position noise alone on ``rows`` (ids; None: every row), for the updates whose noise follows a
        relocation round."""

    def count_in_view(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> int:
        """How many rows can reach ``camera``'s image (a host integer: the policies decide with it per frame)."""
        from ..render.culling import map_in_view

        return int(map_in_view(gmap, camera, T_world_cam, low_pass).numel())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name})"


def leaf_grads(view: RowView) -> dict:
    """The leaves' gradients by name (None where a leaf received none)."""
    return {n: t.grad for n, t in view.leaves.items()}


RAW = PARAM_NAMES
