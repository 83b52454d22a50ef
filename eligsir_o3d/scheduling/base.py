"""The three runtime decisions as small policy interfaces, and the context they act on.

Each EliGSiR mechanism (paper Sec. "Method") is one policy with explicit state and hooks named for when they run;
each ablation swaps it for a plain policy. The Reconstructor calls only these hooks, so it never knows which
policy is active.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from contextlib import contextmanager
from types import SimpleNamespace
from typing import Callable

import torch

from ..core.camera import Camera
from ..core.frame import Frame
from ..core.gaussians import GaussianMap
from ..kernels.base import StepTerms
from ..render import RenderOutput
from .fixed_work import FULL


class MapContext:
    """What a policy may read or change: the map, a renderer call and the running counters. It holds no copies:
    every attribute reads through to its owner (the Reconstructor: ``gmap``, ``device``, ``config.max_gaussians``,
    ``stats.updates``, ``stats.frames_released``, ``_render``), so a map replaced by ``load_ply`` or a restored
    checkpoint is what the policies see next."""

    def __init__(self, owner):
        self._owner = owner

    @classmethod
    def standalone(cls, gmap: GaussianMap, render: Callable[[Camera, object], RenderOutput], device: torch.device,
                   max_gaussians: int) -> "MapContext":
        """A context over a bare map and renderer (tests, tools that drive a policy without a Reconstructor)."""
        stats = SimpleNamespace(updates=0, frames_released=0)
        return cls(SimpleNamespace(gmap=gmap, _render=render, device=device, stats=stats,
                                   config=SimpleNamespace(max_gaussians=max_gaussians)))

    @property
    def gmap(self) -> GaussianMap:
        return self._owner.gmap

    @property
    def device(self) -> torch.device:
        return self._owner.device

    @property
    def max_gaussians(self) -> int:
        return int(self._owner.config.max_gaussians)

    @property
    def updates(self) -> int:
        return self._owner.stats.updates

    @property
    def frames_released(self) -> int:
        return self._owner.stats.frames_released

    @property
    def view(self):
        """The current update's :class:`~..kernels.RowView` (the rows it supervises) while a view-culled update
        runs; None otherwise (the update covers the whole map)."""
        return getattr(self._owner, "view", None)

    def in_view(self, camera: Camera, T_world_cam) -> int:
        """How many Gaussians can reach ``camera``'s image at ``T_world_cam`` (:func:`~..culling.in_view`); the
        map's total where the owner does not cull."""
        optim = getattr(self._owner.config, "optim", None)
        if not getattr(optim, "cull", False):
            return len(self.gmap)
        kernels = getattr(self._owner, "kernels", None)
        if kernels is None:
            from ..kernels import get_kernels

            kernels = get_kernels("auto", self.gmap.device, self.gmap.means.dtype)
        return kernels.count_in_view(self.gmap, camera, T_world_cam)

    @property
    def seed_scale(self) -> float | None:
        """The image scale whose pixels new seeds are spaced in (:meth:`.supervision.SupervisionGrid.seed_scale`):
        the updates' scale where the run's views agree at full resolution; None (the support probe's scale) else."""
        return getattr(self._owner, "seed_scale", None)

    @property
    def plan(self):
        """The current frame's :class:`~.load.FramePlan` (full admission check or not, support render scale)."""
        return getattr(self._owner, "frame_plan", FULL)

    def render(self, camera: Camera, T_world_cam) -> RenderOutput:
        """(camera, T_world_cam) -> RenderOutput of the current map, differentiable."""
        return self._owner._render(camera, T_world_cam)


class Policy(ABC):
    """What every policy shares: a name, its decision counters, and the state a checkpoint saves."""

    name = "policy"

    def counters(self) -> dict:
        """What the policy decided so far (counts for metrics.json and ablation tables)."""
        return {}

    def state_dict(self) -> dict:
        """Everything the next decisions depend on (saved in checkpoints; resume continues identically)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s output."""


class ViewPolicy(Policy):
    """Which released frames are retained, and which retained view supervises the next update."""

    name = "views"
    draining = False  # True while the bounded drain after the stream runs (:meth:`drain`)

    @contextmanager
    def drain(self):
        """Around the bounded drain after the stream (``Reconstructor.finalize``, a budget clock's priced drain),
        where a policy may select differently (:class:`.views.MapGuidedViews`: ``views.drain_replay``)."""
        self.draining = True
        try:
            yield
        finally:
            self.draining = False

    @abstractmethod
    def admit(self, frame: Frame, ctx: MapContext) -> bool:
        """Called once per released source frame; True if the frame is retained for supervision."""
        raise NotImplementedError

    @abstractmethod
    def select(self, rng: torch.Generator) -> Frame:
        """The view for the next optimisation update."""
        raise NotImplementedError

    def bind(self, device, kernels) -> None:
        """Once, from the Reconstructor: the map's device and its kernel set (``eligsir_o3d.kernels``)."""

    def poses_moved(self) -> None:
        """After loop closure moved the retained views' poses: drop what was derived from the old ones."""

    def feedback(self, frame: Frame, out: RenderOutput, error: torch.Tensor, depth: torch.Tensor,
                 camera: Camera) -> None:
        """After an update: the training render's per-pixel error [h, w] (already computed by the loss)."""

    def attach(self, period_s: float | None, cost=None) -> None:
        """When the load changes (``Reconstructor.set_load``): the seconds one source frame grants and the
        ``CostModel`` pricing the work (None without a deterministic budget). A policy whose admission does not
        depend on the budget ignores it."""

    @property
    @abstractmethod
    def views(self) -> list[Frame]:
        raise NotImplementedError


class FidelityPolicy(Policy):
    """At which image scale the next update is supervised."""

    name = "fidelity"

    @abstractmethod
    def scale(self) -> float:
        raise NotImplementedError

    def observe(self, seconds: float, pixels: int, backlog: int) -> None:
        """After an update: its measured cost and the current backlog of unprocessed frames."""

    def at_lowest_scale(self) -> bool:
        """True while the policy supervises at its lowest scale (a policy that does not adapt: never)."""
        return False

    def attach(self, period_s: float | None, cost_fn: Callable[[int], float] | None = None) -> None:
        """When the load changes (``Reconstructor.set_load``): the seconds one source frame grants and, under a
        deterministic budget, the modelled seconds of an update of ``pixels`` supervised pixels. A policy that does
        not adapt to load ignores it."""


class GrowthPolicy(Policy):
    """Where the Gaussian population grows, moves or shrinks."""

    name = "growth"

    @abstractmethod
    def on_frame(self, frame: Frame, admitted: bool, ctx: MapContext) -> int:
        """Called once per released source frame; returns the number of Gaussians added."""
        raise NotImplementedError

    def step_terms(self, ctx: MapContext) -> StepTerms:
        """What the update's step adds on the rows in view: regularisers' weights and position noise (none here)."""
        return StepTerms()

    def post_step(self, frame: Frame, out: RenderOutput, depth: torch.Tensor, camera: Camera, ctx: MapContext) -> None:
        """After the optimizer step (relocation, noise, evidence-gated insertion)."""

    def reseed(self, frames: list[Frame], ctx: MapContext) -> int:
        """Seeds for views admitted before ``ctx.seed_scale`` became finer than what they were seeded at; returns
        the number of Gaussians added (a policy whose seeds do not follow the seed scale adds none)."""
        return 0

    def attach(self, period_s: float | None, cost=None) -> None:
        """When the load changes (``Reconstructor.set_load``): the seconds one source frame grants and the
        ``CostModel`` pricing the work (None without a deterministic budget). A policy whose map size does not
        depend on the budget ignores it."""
