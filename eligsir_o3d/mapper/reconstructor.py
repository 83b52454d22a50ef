"""Reconstructor: the Open3D-style object users integrate RGB-D frames into. It only composes the parts.

    rec = Reconstructor(intrinsic, device="cpu")
    for rgbd, T_world_cam in stream:
        rec.integrate(rgbd, T_world_cam)
    rec.finalize(); rec.save_ply("map.ply")
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np
import open3d as o3d
import torch

from ..budget.cost import priced_gaussians
from ..budget.stages import StageTimes
from ..config import Config
from ..core.camera import Camera, check_pose
from ..core.frame import Frame, FrameError
from ..core.gaussians import EPS2D, GaussianMap
from ..io.checkpoint import read_checkpoint, save_checkpoint
from ..io.ply import load_ply, save_ply
from ..kernels import get_kernels
from ..pose.loop_closure import loop_closure_for
from ..render import RenderOutput, get_renderer
from ..runtime.threads import TORCH_MIN_PIXELS, TORCH_MIN_ROWS, torch_threads
from ..scheduling import MapContext, get_policies
from ..scheduling.coarse_to_fine import install_means_lr_decay
from ..scheduling.fixed_work import FULL, LoadScaledChecks
from ..scheduling.supervision import SupervisionGrid
from .checkpoints import restore
from .intake import checked_pose, to_frame
from .loops import finish_loops, loads_to_loops, track_corrected
from .state import MapperState, StatePart


class Reconstructor:
    """Online RGB-D -> 3D Gaussian map under a bounded optimisation budget (EliGSiR).

    intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` of the incoming images; device: ``"cpu"`` or ``"cuda:0"``.
    ``config`` selects the renderer, the policies (``config.ablate``) and the budget (the Reconstructor keeps a
    resolved copy, ``rec.config``); ``pose_source`` tracks frames integrated with ``pose=None``; ``depth_scale``:
    integer depth / depth_scale = metres (Open3D's spelling; default ``config.depth_scale``, 1000).
    ``offline_frames``: the offline reference over that many source frames (every frame retained and seeded, one
    long coarse-to-fine schedule: ``get_policies(config, offline=True)``); None: the online mapper.

    Composed of its :class:`~.state.MapperState` (``rec.state``: what a checkpoint saves); ``rec.gmap``,
    ``rec.views`` and the other parts below read and assign through to it.
    """

    config, camera, device, gmap, views, fidelity, growth, supervision = (StatePart() for _ in range(8))
    fixed_work, rng, stats, backlog, pose_source, loops, offline_frames = (StatePart() for _ in range(7))

    def __init__(self, intrinsic: o3d.camera.PinholeCameraIntrinsic, device: str = "cpu",
                 config: Config | None = None, pose_source=None, *, depth_scale: float | None = None,
                 offline_frames: int | None = None):
        changes = {"device": str(device)} if depth_scale is None else {"device": str(device),
                                                                        "depth_scale": float(depth_scale)}
        cfg = (config if config is not None else Config()).resolve(**changes)  # a resolved copy
        dev = torch.device(cfg.device)
        camera = intrinsic if isinstance(intrinsic, Camera) else Camera.from_o3d(intrinsic)
        self.renderer = get_renderer(cfg.renderer, dev)
        self.kernels = get_kernels(cfg.optim.kernels, dev)  # the update's select/backward/step
        torch.manual_seed(cfg.seed)
        rng = torch.Generator().manual_seed(cfg.seed)
        gmap = GaussianMap(cfg.sh_degree, dev, cfg.optim.lrs, cfg.optim.adam)
        offline = None if offline_frames is None else int(offline_frames)
        views, fidelity, growth = get_policies(cfg, offline=offline is not None, n_source=offline or 0, camera=camera)
        views.bind(dev, self.kernels)
        self.state = MapperState(
            cfg, camera, dev, gmap, views, fidelity, growth, rng=rng, offline_frames=offline,
            supervision=SupervisionGrid(cfg.supervision),  # area or point samples at reduced scales
            fixed_work=LoadScaledChecks(cfg.fixed_work),  # how much fixed work each frame gets, from the backlog
            pose_source=pose_source, loops=loop_closure_for(cfg.loops, getattr(pose_source, "drifts", False),
                                                            pose_source, cfg.clock.mode == "realtime"))
        self.frame_plan = FULL  # the current frame's plan (the policies' ``MapContext.plan``)
        self.callbacks: list[Callable[["Reconstructor"], None]] = []  # after every update; time excluded
        self.timing = StageTimes()  # wall seconds per stage (admission, growth, update, tracking): stage_times
        self._background = torch.tensor(cfg.background, dtype=torch.float32, device=dev)
        self.view, self.last_in_view = None, None  # the running update's RowView (the rows in view); the last one's size
        self.set_load(0, cfg.clock.frame_period_s)
        if offline is not None:  # the means' step size decays over the offline schedule
            install_means_lr_decay(self, fidelity, cfg.clock.offline_means_lr_final)

    def context(self) -> MapContext:
        """The :class:`~eligsir_o3d.scheduling.MapContext` a policy's hook gets now (built for each call)."""
        count = self.kernels.count_in_view if self.config.optim.cull else None
        return MapContext(self.gmap, self._render, int(self.config.max_gaussians), count, self.stats.updates,
                          self.stats.frames_released, self.frame_plan,
                          self.supervision.seed_scale(self.fidelity.current_scale()), self.view, self.timing)

    # ---- the online loop -------------------------------------------------------------------------------
    def integrate(self, rgbd, pose=None, timestamp: float | None = None, *, updates: int | None = None,
                  deadline: float | None = None) -> dict:
        """Integrate one RGB-D frame (legacy or tensor ``RGBDImage``, or a :class:`Frame`) at ``T_world_cam``.

        Steps: wrap and validate -> admission -> sparse support for new space -> the optimisation budget
        (``updates`` updates, or until ``deadline`` in :meth:`clock_now` seconds; default: config's per-frame budget).
        A bad frame raises :class:`FrameError` before anything in the map changes.
        """
        t0 = time.perf_counter()
        frame = to_frame(rgbd, pose, timestamp, index=self.stats.frames_released, camera=self.camera, config=self.config,
                         last_timestamp=self.stats.last_timestamp, track=self.track)
        self.stats.last_timestamp = frame.timestamp
        self.stats.frames_released += 1
        self.frame_plan = self.fixed_work.plan(self.backlog, self.fidelity.at_lowest_scale())
        with self._threads(self.camera.scaled(self.config.support.scale_for(self.camera)).pixels):
            with self.timing("admission"):
                admitted = self.views.admit(frame, self.context())
                decided = admitted and self.supervision.on_admitted(frame)
            self.stats.frames_admitted += int(admitted)
            with self.timing("growth"):
                ctx = self.context()  # after admission: it may have decided the seed scale
                added = self.growth.on_frame(frame, admitted, ctx)
                if decided:  # seeds may have become finer (seed_scale): the views admitted before get them too
                    added += self.growth.reseed([f for f in self.views.views if f.index != frame.index], ctx)
        self.stats.mapping_s += time.perf_counter() - t0
        if updates is None and deadline is None:
            updates = self.config.clock.updates_per_frame
        done = self.optimize(updates, deadline)
        return {"index": frame.index, "admitted": admitted, "added": added, "updates": done,
                "gaussians": len(self.gmap)}

    def optimize(self, updates: int | None = None, deadline: float | None = None, scale: float | None = None) -> int:
        """Run optimisation updates: ``updates`` of them, or as many as fit before ``deadline`` (:meth:`clock_now`)."""
        done = 0
        while (updates is None or done < updates) and (deadline is None or self.clock_now() < deadline):
            if not self.views.views or len(self.gmap) == 0:
                break
            self._step(scale)
            done += 1
        return done

    def _threads(self, pixels: int):
        """torch's threads for work on images of ``pixels``: ``config.optim.torch_threads`` on the CPU below
        TORCH_MIN_PIXELS pixels and TORCH_MIN_ROWS rows last in view, else the caller's (:mod:`.runtime.threads`)."""
        rows = self.last_in_view or 0
        small = self.device.type == "cpu" and pixels < TORCH_MIN_PIXELS and rows < TORCH_MIN_ROWS
        return torch_threads(self.config.optim.torch_threads if small else 0)

    def finalize(self, deadline: float | None = None) -> None:
        """The bounded drain (the paper's ME state): ``clock.drain_updates`` updates, or fewer by ``deadline``, after
        loop closure's last verification (the map follows the poses it corrects)."""
        finish_loops(self)
        with self.views.drain():
            self.optimize(self.config.clock.drain_updates, deadline)

    def refine(self, steps: int, scale: float | None = None) -> None:
        """``steps`` post-mapping updates (the paper's +N PM), at ``scale`` (default: config.optim.refine_scale)."""
        self.optimize(int(steps), scale=self.config.optim.refine_scale if scale is None else scale)

    def _step(self, scale: float | None) -> None:
        t0 = time.perf_counter()
        with self.timing.sub("scheduling.select"):
            frame = self.views.select(self.rng)
        sample = self.supervision.sample(frame, self.fidelity.scale() if scale is None else scale, self.rng,
                                         self.device)
        with self._threads(sample.camera.pixels):
            self._update(frame, sample)
        dt = time.perf_counter() - t0
        self.stats.updates += 1
        self.stats.supervised_pixels += sample.camera.pixels
        self.stats.mapping_s += dt
        self.timing.add("update", dt)
        self.fidelity.observe(dt, sample.camera.pixels, self.backlog)
        if self.callbacks:
            t1 = time.perf_counter()
            for cb in self.callbacks:
                cb(self)
            self.stats.excluded_s += time.perf_counter() - t1

    def _update(self, frame: Frame, sample) -> None:
        """One update on ``frame``'s view at the pixels of ``sample`` (:class:`.scheduling.supervision.Sample`):
        the kernel set selects the rows in view, the renderer draws them, the kernel set back-propagates the loss
        and steps the rows (with the growth policy's regulariser and noise), then the policies' per-update steps
        (growth's MCMC rounds, the views' feedback)."""
        color, depth, cam, low_pass = sample.color, sample.depth, sample.camera, sample.low_pass
        self.view, out = self._draw_view(frame.T_world_cam, cam, low_pass)
        self.last_in_view = len(self.view)
        self.gmap.note_supervision(sample.fitted)
        ctx = self.context()
        terms = self.growth.step_terms(ctx)
        with self.timing.sub("update.backward"):
            error = self.kernels.backward(out, color, depth, self.config.optim.loss, self.view, terms)
        with self.timing.sub("update.step"):
            self.kernels.step(self.gmap, self.view, terms)
        with self.timing.sub("update.mcmc"):
            self.growth.post_step(frame, out, depth, cam, ctx)
        self.view = None
        with self.timing.sub("scheduling.feedback"):
            self.views.feedback(frame, out, error, depth, cam)

    def _draw_view(self, T_world_cam, cam: Camera, low_pass: float):
        """(view, render) of the rows that can reach ``cam`` at ``T_world_cam``, the view's leaves requiring grad.
        A fused view that held fewer rows than passed its test (known once the render synchronised) is selected
        again with room for them all."""
        capacity = 0
        for _ in range(2):
            with self.timing.sub("update.select"):
                view = self.kernels.select(self.gmap, cam, T_world_cam, low_pass, cull=self.config.optim.cull,
                                           capacity=capacity)
            with self.timing.sub("render"):
                out = self.kernels.draw(self.renderer, view, cam, T_world_cam, self._background, low_pass)
            if not view.overflowed():
                break
            capacity = view.hits()
        return view, out

    def set_load(self, backlog: int, period_s: float | None = None, cost=None) -> None:
        """The load a clock reports: ``backlog`` frames waiting, ``period_s`` seconds that one source frame grants
        (None: unchanged) and, under a deterministic budget, the ``CostModel`` that prices an update (None: the
        fidelity policy measures seconds). The one route by which load reaches the policies and loop closure."""
        self.backlog = int(backlog)
        loads_to_loops(self, self.backlog)  # loop closure's worker stops while the mapper is behind
        if period_s is not None:
            cost_fn = None if cost is None else (lambda pixels: cost.update(pixels, priced_gaussians(self)))
            self.fidelity.attach(period_s, cost_fn)
            self.growth.attach(period_s, cost)  # the budget cap on the map size (scheduling.capacity)
            self.views.attach(period_s, cost)  # the pose pre-filter's spacing (scheduling.spacing)

    def policy_counters(self) -> dict:
        """Each policy's name and what it decided so far (admissions, seeds, insertions, relocations, scales)."""
        counters = {kind: {"policy": p.name, **p.counters()} for kind, p in self.state.policies()}
        return {**counters, "fixed_work": {"policy": self.fixed_work.name, **self.fixed_work.counters()},
                "supervision": {"policy": self.supervision.name, **self.supervision.counters()}}

    def clock_now(self) -> float:
        """``time.perf_counter()`` minus the time spent in callbacks: the mapper's own clock for real-time replay."""
        return time.perf_counter() - self.stats.excluded_s

    def warmup(self) -> float:
        """Pay first-use costs (numba compilation or cache load, CUDA kernel loading; an explicit ``gsplat`` not built
        yet compiles here, logged) before a stream, on a scratch scene (:func:`.optim.warmup.warm_up`): seconds."""
        from ..optim.warmup import warm_up

        return warm_up(self.renderer, self.config.optim.loss, self.device, self._background, self.kernels,
                       self.config.sh_degree)

    def calibrate(self, frames=None, *, cache: bool = True, **kw):
        """Fit the budget's cost model to this machine, device and renderer: time a few updates at each
        supervision scale in a scratch Reconstructor (this one's map is untouched) on ``frames`` (Frames with
        poses; default: the embedded synthetic room at this camera's size). With ``cache``, the fit is cached per
        machine/device/renderer under the user's cache directory and reused. Returns (CostModel, info)."""
        from ..budget.calibrate import cached_cost_model, calibrate

        return cached_cost_model(self, frames, **kw) if cache else calibrate(self, frames, **kw)

    # ---- state and checkpoints ------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything the next decisions depend on (:meth:`.state.MapperState.state_dict`)."""
        return self.state.state_dict()

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s output; transactional (:meth:`.state.MapperState.load_state_dict`)."""
        self.state.load_state_dict(state)

    def save(self, path: str | Path, *, extra: dict | None = None, sequence=None) -> Path:
        """Checkpoint the state to ``path`` atomically; ``extra``: a caller's dict; ``sequence``: its frames by reference."""
        return save_checkpoint(self.state_dict(), path, extra=extra, sequence=sequence)

    @classmethod
    def load(cls, path: str | Path, device: str | None = None, *, sequence=None, pose_source=None,
             setup: Callable[["Reconstructor"], None] | None = None) -> "Reconstructor":
        """A Reconstructor restored from :meth:`save`'s checkpoint, continuing where it stopped (:func:`.restore`)."""
        return cls.from_checkpoint(read_checkpoint(path, sequence=sequence), device, pose_source=pose_source,
                                   setup=setup)

    @classmethod
    def from_checkpoint(cls, ck: dict, device: str | None = None, *, pose_source=None,
                        setup: Callable[["Reconstructor"], None] | None = None) -> "Reconstructor":
        """A Reconstructor built from a decoded checkpoint (``read_checkpoint``'s dict; :func:`.checkpoints.restore`)."""
        return restore(cls, ck, device, pose_source=pose_source, setup=setup)

    def save_ply(self, path: str | Path) -> Path:
        """Write the map as a standard 3DGS PLY (atomic replace)."""
        return save_ply(self.gmap, path)

    def load_ply(self, path: str | Path) -> None:
        """Replace the map with the Gaussians of a 3DGS PLY (optimizer state starts fresh)."""
        self.gmap = load_ply(path, self.device, self.config.optim.lrs, self.config.optim.adam)
        self.config.sh_degree = self.gmap.sh_degree

    # ---- rendering -------------------------------------------------------------------------------------
    def _render(self, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> RenderOutput:
        """The map at ``camera``/``T_world_cam``; with ``config.optim.cull`` only the rows in view are drawn (the
        same image; per-Gaussian outputs such as radii are then the kept rows')."""
        with torch.no_grad():
            view = self.kernels.select(self.gmap, camera, T_world_cam, low_pass, cull=self.config.optim.cull,
                                       grad=False)
            with self.timing.sub("render"):
                return self.renderer.render(*view.render_args(), camera, T_world_cam, self._background,
                                            low_pass=low_pass)

    @torch.no_grad()
    def render(self, pose, intrinsic: o3d.camera.PinholeCameraIntrinsic | Camera | None = None,
               scale: float = 1.0) -> RenderOutput:
        """Render colour [H, W, 3], depth [H, W] (metres) and alpha [H, W] at ``T_world_cam`` ``pose``, with the
        low-pass of the resolution the map was supervised at (:meth:`.GaussianMap.low_pass`)."""
        cam = self.camera if intrinsic is None else (intrinsic if isinstance(intrinsic, Camera)
                                                     else Camera.from_o3d(intrinsic))
        T = check_pose(pose, "render pose")
        cam = cam.scaled(scale)
        out = self._render(cam, T, self.gmap.low_pass(cam))
        out.color = out.color.clamp(0.0, 1.0)
        return out

    def track(self, frame: Frame, gt_pose: np.ndarray | None = None) -> np.ndarray:
        """``frame``'s T_world_cam from the pose source, timed as tracking. The first tracked frame is anchored at
        ``gt_pose`` when one is given (so the map lives in the ground truth's frame and fixed evaluation poses see
        it); later frames ignore it. Raises :class:`FrameError` without a pose source or for an invalid pose."""
        if self.pose_source is None:
            raise FrameError(f"frame {frame.index}: no pose given and no pose source configured "
                             "(pass T_world_cam, or Reconstructor(..., pose_source=get_pose_source('odometry')))")
        anchor = gt_pose if self.stats.frames_tracked == 0 else None
        t0 = time.perf_counter()
        try:
            T = self.pose_source.track(frame.index, frame.timestamp, frame.color, frame.depth, frame.camera,
                                       gt_pose=anchor)
        finally:
            self.stats.tracking_s += time.perf_counter() - t0
            self.timing.add("tracking", time.perf_counter() - t0)
        T = checked_pose(T, frame.index)
        self.stats.frames_tracked += 1
        return T if self.loops is None else track_corrected(self, frame, T)  # loop closure: mapper.loops

    def extract_point_cloud(self, min_opacity: float = 0.1, **kw) -> o3d.geometry.PointCloud:
        """Gaussian centres with SH-DC colour and normals (oriented toward the retained views' cameras)."""
        from ..export import extract_point_cloud

        kw.setdefault("poses", [f.T_world_cam for f in self.views.views])
        return extract_point_cloud(self.gmap, min_opacity, **kw)

    def extract_triangle_mesh(self, poses=None, voxel_size: float = 0.02, depth_max: float = 5.0,
                              scale: float = 0.5, **kw) -> o3d.geometry.TriangleMesh:
        """TSDF mesh (Open3D VoxelBlockGrid) of depth and colour rendered from the map at ``poses``
        (default: the retained views' poses), rendered at ``scale`` of the camera with the map's low-pass."""
        from ..export import extract_triangle_mesh

        poses = [f.T_world_cam for f in self.views.views] if poses is None else list(poses)
        with torch.no_grad():
            return extract_triangle_mesh(lambda cam, T: self._render(cam, T, self.gmap.low_pass(cam)), poses,
                                         self.camera.scaled(scale), voxel_size=voxel_size, depth_max=depth_max, **kw)

    def __repr__(self) -> str:
        return (f"Reconstructor({self.camera.width}x{self.camera.height}, device={self.device}, renderer="
                f"{self.config.renderer}, gaussians={len(self.gmap)}, updates={self.stats.updates})")
