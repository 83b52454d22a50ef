"""The three runtime decisions as small policy interfaces, and the context they act on.

Each EliGSiR mechanism (paper Sec. "Method") is one policy with explicit state and hooks named for when they run;
each ablation swaps it for a plain policy. The Reconstructor calls only these hooks, so it never knows which
policy is active.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import torch

from ..core.camera import Camera
from ..core.frame import Frame
from ..core.gaussians import GaussianMap
from ..budget.stages import StageTimes
from ..kernels.base import RowView, StepTerms
from ..render import RenderOutput
from .fixed_work import FULL, FramePlan


@dataclass
class MapContext:
    """What a policy's hook may read or change, handed to it by the caller for that one call (as gsplat's
    strategies take the parameters, optimizers and step): the map, a renderer call, the map-size limit and the
    counters and per-frame decisions of this moment. The Reconstructor builds one per hook call
    (``Reconstructor.context``), so a map replaced by ``load_ply`` or a restored checkpoint is what the next hook
    sees; a test or tool that drives a policy without a Reconstructor builds one from a bare map and renderer.

    Args:
        gmap: the map the policy reads and grows.
        render: ``(camera, T_world_cam) -> RenderOutput`` of the current map.
        max_gaussians: the map-size limit (memory).
        count_in_view: ``(gmap, camera, T_world_cam) -> int``, the Gaussians of ``gmap`` that can reach that
            image (``KernelSet.count_in_view``); None: every Gaussian counts (the map is not culled).
        updates, frames_released: the mapper's counters now.
        plan: the current frame's :class:`~.fixed_work.FramePlan` (full admission check or not, probe scale).
        seed_scale: the image scale whose pixels new seeds are spaced in
            (:meth:`.supervision.SupervisionGrid.seed_scale`); None: the support probe's scale.
        view: the running update's :class:`~..kernels.RowView` (the rows it supervises); None outside an update.
        timing: where a hook's sub-stages are timed (:meth:`~..budget.stages.StageTimes.sub`).
    """

    gmap: GaussianMap
    render: Callable[[Camera, object], RenderOutput]
    max_gaussians: int
    count_in_view: Callable[[GaussianMap, Camera, object], int] | None = None
    updates: int = 0
    frames_released: int = 0
    plan: FramePlan = FULL
    seed_scale: float | None = None
    view: RowView | None = None
    timing: StageTimes = field(default_factory=StageTimes)

    @property
    def device(self) -> torch.device:
        return self.gmap.device

    def in_view(self, camera: Camera, T_world_cam) -> int:
        """How many Gaussians can reach ``camera``'s image at ``T_world_cam``; the map's size without a count."""
        return len(self.gmap) if self.count_in_view is None else int(self.count_in_view(self.gmap, camera, T_world_cam))


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

    def current_scale(self) -> float:
        """The scale :meth:`scale` would give now, without handing it out (a policy that records what it handed
        out, to tell its own measurements from explicit scales, records nothing here)."""
        return self.scale()

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
