"""What a Reconstructor's next decisions depend on, in one object: :class:`MapperState` holds the map, the three
policies, the supervision and fixed-work choosers, the counters, the random generators, the pose source and loop
closure, and turns them into one plain dict (:meth:`MapperState.state_dict`) and back
(:meth:`MapperState.load_state_dict`). The Reconstructor is composed of one (``rec.state``); its attributes of the
same names read and assign through to it (:class:`StatePart`). A checkpoint file encodes this dict
(:mod:`eligsir_o3d.io.checkpoint`)."""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from ..config import Config
from ..core.camera import Camera
from ..core.gaussians import GaussianMap
from ..scheduling import FidelityPolicy, GrowthPolicy, ViewPolicy


@dataclass
class MappingStats:
    """Compute accounting of the paper's protocol (evaluation callbacks excluded from the time)."""

    frames_released: int = 0
    frames_admitted: int = 0
    updates: int = 0
    supervised_pixels: int = 0  # sum of image sizes of every supervised view over all updates
    mapping_s: float = 0.0
    tracking_s: float = 0.0
    frames_tracked: int = 0  # frames whose pose came from the pose source (the first one is anchored)
    excluded_s: float = 0.0  # wall time of evaluation callbacks, checkpoint I/O and (pipeline) decoding the recording
    last_timestamp: float | None = None  # of the last integrated frame: timestamps must increase

    @property
    def supervised_mpix(self) -> float:
        return self.supervised_pixels / 1e6


@dataclass
class MapperState:
    """The parts of a mapper that a checkpoint saves and a resumed run continues from.

    Args:
        config: the resolved Config; camera: the stream's; device: the map's.
        gmap: the Gaussians with their Adam moments.
        views: the view-scheduling policy (:func:`eligsir_o3d.scheduling.get_policies` makes all three).
        fidelity: the fidelity policy.
        growth: the growth policy.
        supervision: the supervision sampler (:class:`~eligsir_o3d.scheduling.supervision.SupervisionGrid`).
        fixed_work: the per-frame fixed-work chooser (:class:`~eligsir_o3d.scheduling.fixed_work.LoadScaledChecks`).
        rng: the mapper's own generator (view choice, supervision samples).
        stats: the counters; backlog: frames waiting (the clock's report).
        pose_source: what tracks frames integrated without a pose; loops: loop closure (None: off).
        offline_frames: the offline reference's source frames (None: the online mapper).
    """

    config: Config
    camera: Camera
    device: torch.device
    gmap: GaussianMap
    views: ViewPolicy
    fidelity: FidelityPolicy
    growth: GrowthPolicy
    supervision: Any
    fixed_work: Any
    rng: torch.Generator
    stats: MappingStats = dataclasses.field(default_factory=MappingStats)
    backlog: int = 0
    pose_source: Any = None
    loops: Any = None
    offline_frames: int | None = None

    def policies(self):
        """(name, policy) of the three mechanisms, in checkpoint order."""
        return (("views", self.views), ("fidelity", self.fidelity), ("growth", self.growth))

    def state_dict(self) -> dict:
        """Everything the next decisions depend on: config and camera, the Gaussians with their Adam moments, the
        three policies' states, the retained views, the counters, the random generators and the pose source's
        state. Plain containers, tensors, arrays, Frames and Cameras (what ``save_checkpoint`` encodes)."""
        return {
            "config": self.config.to_dict(),
            "camera": dataclasses.asdict(self.camera),
            "device": str(self.device),
            "retained_views": list(self.views.views),  # first, so a policy state holding their tensors refers to them
            "gmap": self.gmap.state_dict(),
            "policies": {name: {"class": type(p).__name__, "state": p.state_dict()} for name, p in self.policies()},
            "retained": [{"index": int(f.index), "timestamp": float(f.timestamp)} for f in self.views.views],
            "stats": dataclasses.asdict(self.stats),
            "backlog": self.backlog,
            "rng": self.rng.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if self.device.type == "cuda" else None,
            "pose_source": self.pose_source.state_dict() if hasattr(self.pose_source, "state_dict") else None,
            "fixed_work": self.fixed_work.state_dict(),
            "supervision": self.supervision.state_dict(),
            "offline_frames": self.offline_frames,  # the offline reference's policies (None: online)
            "loops": None if self.loops is None else self.loops.state_dict(),  # loop closure (pose.loop_closure)
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s output (saved with the same config and policies). Raises ValueError when a
        policy class differs or the view policy does not restore its retained views. Transactional: a state that
        fails half-way (a malformed policy state, a missing key) leaves this state as it was (a copy of it is put
        back) and the error is raised."""
        backup = copy.deepcopy(self.state_dict())
        try:
            self._restore(state)
        except BaseException:
            self._restore(backup)
            raise

    def _restore(self, state: dict) -> None:
        for name, policy in self.policies():
            saved = state["policies"][name]
            if type(policy).__name__ != saved["class"]:
                raise ValueError(f"the {name} policy was {saved['class']} when saved but the config builds "
                                 f"{type(policy).__name__} (a policy replaced after construction must be replaced "
                                 f"again: Reconstructor.load(..., setup=fn))")
        self.gmap.load_state_dict(state["gmap"])
        for name, policy in self.policies():
            policy.load_state_dict(state["policies"][name]["state"])
        restored = [(int(f.index), float(f.timestamp)) for f in self.views.views]
        expected = [(int(v["index"]), float(v["timestamp"])) for v in state["retained"]]
        if restored != expected:
            raise ValueError(
                f"the {state['policies']['views']['class']} view policy restored {len(restored)} retained views "
                f"but {len(expected)} were saved: its state_dict() must include its retained views (Frame objects "
                f"or their tensors) and load_state_dict() must put them back")
        known = {f.name for f in dataclasses.fields(self.stats)}
        for k, v in state["stats"].items():
            if k in known:
                setattr(self.stats, k, v)
        self.backlog = state.get("backlog", 0)
        self.fixed_work.load_state_dict(state.get("fixed_work", {}))
        self.supervision.load_state_dict(state.get("supervision", {}))
        self.rng.set_state(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        if state.get("cuda_rng") is not None and self.device.type == "cuda":
            torch.cuda.set_rng_state_all(state["cuda_rng"])
        if self.loops is not None and state.get("loops") is not None:
            self.loops.load_state_dict(state["loops"])
            self.gmap.anchor_view = self.loops.anchor
        if state.get("pose_source") is not None and hasattr(self.pose_source, "load_state_dict"):
            self.pose_source.load_state_dict(state["pose_source"])


class StatePart:
    """A Reconstructor attribute that lives in its :class:`MapperState`: read and assigned through
    (``rec.gmap`` is ``rec.state.gmap``)."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, objtype=None):
        return self if obj is None else getattr(obj.state, self.name)

    def __set__(self, obj, value) -> None:
        setattr(obj.state, self.name, value)
