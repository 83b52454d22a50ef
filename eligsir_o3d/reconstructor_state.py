"""The Reconstructor's state (a mixin of :class:`~eligsir_o3d.reconstructor.Reconstructor`): everything its next
decisions depend on as one plain dict (:meth:`~ReconstructorState.state_dict`), restored by
:meth:`~ReconstructorState.load_state_dict`, the checkpoint file round trip (``save`` / ``load`` /
``from_checkpoint``; :mod:`eligsir_o3d.io.checkpoint` only encodes the dict) and the map alone as a 3DGS PLY
(``save_ply`` / ``load_ply``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import torch

from .config import Config
from .core.camera import Camera
from .io.checkpoint import CheckpointError, read_checkpoint, save_checkpoint


class ReconstructorState:
    """State and checkpoints of a Reconstructor (its attributes: config, camera, device, gmap, the three policies,
    stats, backlog, rng, pose_source, fixed_work, supervision, offline_frames)."""

    def save(self, path: str | Path, *, extra: dict | None = None, sequence=None) -> Path:
        """Checkpoint the full mapper state (:meth:`state_dict`) to ``path``, atomically; ``extra``: a caller's
        plain dict stored beside it; ``sequence``: views that are its frames are stored as references."""
        return save_checkpoint(self.state_dict(), path, extra=extra, sequence=sequence)

    @classmethod
    def load(cls, path: str | Path, device: str | None = None, *, sequence=None, pose_source=None,
             setup: Callable[["ReconstructorState"], None] | None = None) -> "ReconstructorState":
        """A Reconstructor restored from :meth:`save`'s checkpoint; it continues where the saved one stopped."""
        return cls.from_checkpoint(read_checkpoint(path, sequence=sequence), device, pose_source=pose_source,
                                   setup=setup)

    @classmethod
    def from_checkpoint(cls, ck: dict, device: str | None = None, *, pose_source=None,
                        setup: Callable[["ReconstructorState"], None] | None = None) -> "ReconstructorState":
        """A Reconstructor built from a decoded checkpoint (``read_checkpoint``'s dict; its ``extra`` is the
        caller's). device: default where it was saved (the renderer is re-chosen when the device type changes).
        setup: called with the fresh Reconstructor before the state is restored, for a caller that replaces
        policies after construction to do the same again (the offline reference needs none: its policies come from
        ``get_policies(config, offline=True)`` and ``offline_frames`` is part of the state)."""
        path = ck.get("path", "checkpoint")
        if ck.get("unresolved_views"):
            raise CheckpointError(f"{path}: {ck['unresolved_views']} views were saved as references to a sequence; "
                                  f"pass sequence= (the one given when saving) to load it")
        cfg = Config.from_dict(ck["config"])
        saved_dev = torch.device(ck["device"])
        dev = torch.device(device) if device is not None else saved_dev
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise CheckpointError(f"{path}: saved on {saved_dev}, but CUDA is not available here; "
                                  f"pass device='cpu' to load it on the CPU")
        if dev.type != saved_dev.type:
            cfg.renderer = "auto"
        rec = cls(Camera(**ck["camera"]), str(dev), cfg, pose_source=pose_source, offline_frames=ck.get("offline_frames"))
        if setup is not None:
            setup(rec)
        try:
            rec.load_state_dict(ck)
        except ValueError as e:
            raise CheckpointError(f"{path}: {e}") from None
        return rec

    def save_ply(self, path: str | Path) -> Path:
        """Write the map as a standard 3DGS PLY (atomic replace)."""
        from .io.ply import save_ply

        return save_ply(self.gmap, path)

    def load_ply(self, path: str | Path) -> None:
        """Replace the map with the Gaussians of a 3DGS PLY (optimizer state starts fresh)."""
        from .io.ply import load_ply

        gmap = load_ply(path, self.device, self.config.optim.lrs, self.config.optim.adam)
        self.gmap = gmap
        self.config.sh_degree = gmap.sh_degree

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
            "policies": {name: {"class": type(p).__name__, "state": p.state_dict()}
                         for name, p in self._policies()},
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
        """Restore :meth:`state_dict`'s output into this Reconstructor (built with the same config and policies).
        Raises ValueError when a policy class differs or the view policy does not restore its retained views.
        Transactional: a state that fails half-way (a malformed policy state, a missing key) leaves this
        Reconstructor as it was (a copy of its own state is put back) and the error is raised."""
        import copy

        backup = copy.deepcopy(self.state_dict())
        try:
            self._load_state_dict(state)
        except BaseException:
            self._load_state_dict(backup)
            raise

    def _load_state_dict(self, state: dict) -> None:
        for name, policy in self._policies():
            saved = state["policies"][name]
            if type(policy).__name__ != saved["class"]:
                raise ValueError(f"the {name} policy was {saved['class']} when saved but the config builds "
                                 f"{type(policy).__name__} (a policy replaced after construction must be replaced "
                                 f"again: Reconstructor.load(..., setup=fn))")
        self.gmap.load_state_dict(state["gmap"])
        for name, policy in self._policies():
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
        self.supervision.load_state_dict(state.get("supervision", {}))  # older checkpoints: undecided
        self.rng.set_state(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        if state.get("cuda_rng") is not None and self.device.type == "cuda":
            torch.cuda.set_rng_state_all(state["cuda_rng"])
        if self.loops is not None and state.get("loops") is not None:
            self.loops.load_state_dict(state["loops"])
            self.gmap.anchor_view = self.loops.anchor
        if state.get("pose_source") is not None and hasattr(self.pose_source, "load_state_dict"):
            self.pose_source.load_state_dict(state["pose_source"])

    def _policies(self):
        return (("views", self.views), ("fidelity", self.fidelity), ("growth", self.growth))
