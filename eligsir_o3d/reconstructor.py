"""Reconstructor: the Open3D-style object users integrate RGB-D frames into. It only composes the parts.

    rec = Reconstructor(intrinsic, device="cpu")
    for rgbd, T_world_cam in stream:
        rec.integrate(rgbd, T_world_cam)
    rec.finalize(); rec.save_ply("map.ply")
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import open3d as o3d
import torch

from .core.camera import Camera, check_pose
from .budget.stages import StageTimes
from .budget.cost import priced_gaussians
from .config import Config
from .core.frame import Frame, FrameError
from .core.gaussians import EPS2D, GaussianMap
from .kernels import get_kernels
from .runtime.threads import TORCH_MIN_PIXELS, TORCH_MIN_ROWS, torch_threads
from .optim.losses import supervision_loss
from .pose.loop_closure import loop_closure_for, track_corrected
from .reconstructor_state import ReconstructorState
from .render import RenderOutput, get_renderer
from .scheduling import MapContext, get_policies
from .scheduling.coarse_to_fine import install_means_lr_decay
from .scheduling.fixed_work import FULL, LoadScaledChecks
from .scheduling.supervision import SupervisionGrid


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


class Reconstructor(ReconstructorState):
    """Online RGB-D -> 3D Gaussian map under a bounded optimisation budget (EliGSiR).

    intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` of the incoming images; device: ``"cpu"`` or ``"cuda:0"``.
    ``config`` selects the renderer, the policies (``config.ablate``) and the budget (the Reconstructor keeps a
    resolved copy, ``rec.config``); ``pose_source`` tracks frames integrated with ``pose=None``; ``depth_scale``:
    integer depth / depth_scale = metres (Open3D's spelling; default ``config.depth_scale``, 1000).
    ``offline_frames``: the offline reference over that many source frames (every frame retained and seeded, one
    long coarse-to-fine schedule: ``get_policies(config, offline=True)``); None: the online mapper.
    """

    def __init__(self, intrinsic: o3d.camera.PinholeCameraIntrinsic, device: str = "cpu",
                 config: Config | None = None, pose_source=None, *, depth_scale: float | None = None,
                 offline_frames: int | None = None):
        changes = {"device": str(device)} if depth_scale is None else {"device": str(device),
                                                                        "depth_scale": float(depth_scale)}
        self.config = (config if config is not None else Config()).resolve(**changes)  # a resolved copy
        self.device = torch.device(self.config.device)
        self.camera = intrinsic if isinstance(intrinsic, Camera) else Camera.from_o3d(intrinsic)
        self.renderer = get_renderer(self.config.renderer, self.device)
        self.kernels = get_kernels(self.config.optim.kernels, self.device)  # the update's select/backward/step
        torch.manual_seed(self.config.seed)
        self.rng = torch.Generator().manual_seed(self.config.seed)
        self.gmap = GaussianMap(self.config.sh_degree, self.device, self.config.optim.lrs, self.config.optim.adam)
        self.offline_frames = None if offline_frames is None else int(offline_frames)
        self.views, self.fidelity, self.growth = get_policies(self.config, offline=self.offline_frames is not None,
                                                              n_source=self.offline_frames or 0, camera=self.camera)
        self.views.bind(self.device, self.kernels)
        self.supervision = SupervisionGrid(self.config.supervision)  # area or point samples at reduced scales
        self.fixed_work = LoadScaledChecks(self.config.fixed_work)  # how much fixed work each frame gets, from the backlog
        self.frame_plan = FULL  # the current frame's plan (read by the policies through ctx.plan)
        self.ctx = MapContext(self)
        self.pose_source = pose_source
        self.loops = loop_closure_for(self.config.loops, getattr(pose_source, "drifts", False), pose_source)
        self.stats = MappingStats()
        self.backlog = 0  # frames waiting to be integrated (set_load, by a clock)
        self.callbacks: list[Callable[["Reconstructor"], None]] = []  # after every update; time excluded
        self.timing = StageTimes()  # wall seconds per stage (admission, growth, update, tracking): stage_times
        self._background = torch.tensor(self.config.background, dtype=torch.float32, device=self.device)
        self.view, self.last_in_view = None, None  # the running update's RowView (the rows in view); the last one's size
        self.set_load(0, self.config.clock.frame_period_s)
        if self.offline_frames is not None:  # the means' step size decays over the offline schedule
            install_means_lr_decay(self, self.fidelity, self.config.clock.offline_means_lr_final)

    # ---- the online loop -------------------------------------------------------------------------------
    def integrate(self, rgbd, pose=None, timestamp: float | None = None, *, updates: int | None = None,
                  deadline: float | None = None) -> dict:
        """Integrate one RGB-D frame (legacy or tensor ``RGBDImage``, or a :class:`Frame`) at ``T_world_cam``.

        Steps: wrap and validate -> admission -> sparse support for new space -> the optimisation budget
        (``updates`` updates, or until ``deadline`` in :meth:`clock_now` seconds; default: config's per-frame budget).
        A bad frame raises :class:`FrameError` before anything in the map changes.
        """
        t0 = time.perf_counter()
        frame = self._to_frame(rgbd, pose, timestamp)
        self.stats.last_timestamp = frame.timestamp
        self.stats.frames_released += 1
        self.frame_plan = self.fixed_work.plan(self.backlog, self.fidelity.at_lowest_scale())
        with self._threads(self.camera.scaled(self.config.support.scale_for(self.camera)).pixels):
            with self.timing("admission"):
                admitted = self.views.admit(frame, self.ctx)
                decided = admitted and self.supervision.on_admitted(frame)
            self.stats.frames_admitted += int(admitted)
            with self.timing("growth"):
                added = self.growth.on_frame(frame, admitted, self.ctx)
                if decided:  # seeds may have become finer (seed_scale): the views admitted before get them too
                    added += self.growth.reseed([f for f in self.views.views if f.index != frame.index], self.ctx)
        self.stats.mapping_s += time.perf_counter() - t0
        if updates is None and deadline is None:
            updates = self.config.clock.updates_per_frame
        done = self.optimize(updates, deadline)
        return {"index": frame.index, "admitted": admitted, "added": added, "updates": done,
                "gaussians": len(self.gmap)}

    @property
    def seed_scale(self) -> float | None:
        """The scale new seeds are spaced in (``MapContext.seed_scale``): the supervision's choice at today's scale."""
        return self.supervision.seed_scale(self.fidelity.scale())

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
        """The bounded drain (the paper's ME state): ``clock.drain_updates`` updates, or fewer by ``deadline``."""
        with self.views.drain():
            self.optimize(self.config.clock.drain_updates, deadline)

    def refine(self, steps: int, scale: float | None = None) -> None:
        """``steps`` post-mapping updates (the paper's +N PM), at ``scale`` (default: config.optim.refine_scale)."""
        self.optimize(int(steps), scale=self.config.optim.refine_scale if scale is None else scale)

    def _step(self, scale: float | None) -> None:
        t0 = time.perf_counter()
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
        terms = self.growth.step_terms(self.ctx)
        error = self.kernels.backward(out, color, depth, self.config.optim.loss, self.view, terms)
        self.kernels.step(self.gmap, self.view, terms)
        self.growth.post_step(frame, out, depth, cam, self.ctx)
        self.view = None
        self.views.feedback(frame, out, error, depth, cam)

    def _draw_view(self, T_world_cam, cam: Camera, low_pass: float):
        """(view, render) of the rows that can reach ``cam`` at ``T_world_cam``, the view's leaves requiring grad.
        A fused view that held fewer rows than
        passed its test (known once the render synchronised) is selected again with room for them all."""
        capacity = 0
        for _ in range(2):
            view = self.kernels.select(self.gmap, cam, T_world_cam, low_pass, cull=self.config.optim.cull,
                                       capacity=capacity)
            out = self.renderer.render(*view.render_args(), cam, T_world_cam, self._background, low_pass=low_pass)
            if not view.overflowed():
                break
            capacity = view.hits()
        return view, out

    def set_load(self, backlog: int, period_s: float | None = None, cost=None) -> None:
        """The load a clock reports: ``backlog`` frames waiting, ``period_s`` seconds that one source frame grants
        (None: unchanged) and, under a deterministic budget, the ``CostModel`` that prices an update (None: the
        fidelity policy measures seconds). The one route by which load reaches the fidelity policy."""
        self.backlog = int(backlog)
        if period_s is not None:
            cost_fn = None if cost is None else (lambda pixels: cost.update(pixels, priced_gaussians(self)))
            self.fidelity.attach(period_s, cost_fn)
            self.growth.attach(period_s, cost)  # the budget cap on the map size (scheduling.capacity)
            self.views.attach(period_s, cost)  # the pose pre-filter's spacing (scheduling.spacing)

    def policy_counters(self) -> dict:
        """Each policy's name and what it decided so far (admissions, seeds, insertions, relocations, scales)."""
        counters = {kind: {"policy": p.name, **p.counters()} for kind, p in self._policies()}
        return {**counters, "fixed_work": {"policy": self.fixed_work.name, **self.fixed_work.counters()},
                "supervision": {"policy": self.supervision.name, **self.supervision.counters()}}

    def clock_now(self) -> float:
        """``time.perf_counter()`` minus the time spent in callbacks: the mapper's own clock for real-time replay."""
        return time.perf_counter() - self.stats.excluded_s

    def warmup(self) -> float:
        """Render a one-Gaussian scene and back-propagate the supervision loss through it, so that first-use costs
        (numba compilation or cache load for ``cpu`` and the CPU D-SSIM, CUDA kernel loading for ``gsplat``) are
        paid before a live stream starts rather than on its first frames. Returns the seconds it took; the map is
        untouched. With an explicit ``gsplat`` renderer whose extension is not built yet, this includes gsplat's
        one-time JIT compile (minutes), which is logged when it starts and ends (``auto`` compiles it when it
        chooses the renderer instead)."""
        t0 = time.perf_counter()
        dev = self.device
        means = torch.tensor([[0.0, 0.0, 1.0]], device=dev, requires_grad=True)
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=dev)
        scales, colors = torch.full((1, 3), 0.1, device=dev), torch.full((1, 3), 0.5, device=dev)
        opacities = torch.full((1,), 0.5, device=dev)
        out = self.renderer.render(means, quats, scales, opacities, colors, Camera(16, 16, 16.0, 16.0, 7.5, 7.5),
                                   np.eye(4), self._background)
        loss = supervision_loss(out, torch.zeros_like(out.color), torch.ones_like(out.depth), self.config.optim.loss)[0]
        (loss + out.alpha.sum()).backward()  # the loss's own compiled kernels (D-SSIM on the CPU) load here too
        return time.perf_counter() - t0

    def calibrate(self, frames=None, *, cache: bool = True, **kw):
        """Fit the budget's cost model to this machine, device and renderer: time a few updates at each
        supervision scale in a scratch Reconstructor (this one's map is untouched) on ``frames`` (Frames with
        poses; default: the embedded synthetic room at this camera's size). With ``cache``, the fit is cached per
        machine/device/renderer under the user's cache directory and reused. Returns (CostModel, info)."""
        from .budget.calibrate import cached_cost_model, calibrate

        return cached_cost_model(self, frames, **kw) if cache else calibrate(self, frames, **kw)

    # ---- rendering -------------------------------------------------------------------------------------
    def _render(self, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> RenderOutput:
        """The map at ``camera``/``T_world_cam``; with ``config.optim.cull`` only the rows in view are drawn (the
        same image; per-Gaussian outputs such as radii are then the kept rows')."""
        with torch.no_grad():
            view = self.kernels.select(self.gmap, camera, T_world_cam, low_pass, cull=self.config.optim.cull,
                                       grad=False)
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

    # ---- input -----------------------------------------------------------------------------------------
    def _to_frame(self, rgbd, pose, timestamp) -> Frame:
        index = self.stats.frames_released
        ts = float(timestamp) if timestamp is not None else index * self.config.clock.frame_period_s
        if isinstance(rgbd, Frame):
            frame = rgbd
            if pose is not None:
                frame.T_world_cam = self._checked(pose, frame.index)
        else:
            given = np.eye(4) if pose is None else pose  # no pose: decoded at the identity, then tracked
            frame = Frame.from_rgbd(rgbd, self.camera, given, depth_scale=self.config.depth_scale,
                                    depth_max=self.config.depth_max, timestamp=ts, index=index)
            if pose is None:
                frame.T_world_cam = self.track(frame)
        if frame.camera != self.camera:
            raise FrameError(f"frame {frame.index}: camera {frame.camera} differs from the reconstructor's {self.camera}")
        last = self.stats.last_timestamp
        if last is not None and not frame.timestamp > last:
            raise FrameError(f"frame {frame.index}: timestamp {frame.timestamp:g} s is not after the previous "
                             f"frame's {last:g} s (timestamps must increase)")
        return frame

    def _checked(self, pose, index: int) -> np.ndarray:
        try:
            return check_pose(pose, f"frame {index}: pose")
        except ValueError as e:
            raise FrameError(str(e)) from None

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
        T = self._checked(T, frame.index)
        self.stats.frames_tracked += 1
        return T if self.loops is None else track_corrected(self, frame, T)  # loop closure: pose.loop_closure

    # ---- geometry export -------------------------------------------------------------------------------
    def extract_point_cloud(self, min_opacity: float = 0.1, **kw) -> o3d.geometry.PointCloud:
        """Gaussian centres with SH-DC colour and normals (oriented toward the retained views' cameras)."""
        from .export import extract_point_cloud

        kw.setdefault("poses", [f.T_world_cam for f in self.views.views])
        return extract_point_cloud(self.gmap, min_opacity, **kw)

    def extract_triangle_mesh(self, poses=None, voxel_size: float = 0.02, depth_max: float = 5.0,
                              scale: float = 0.5, **kw) -> o3d.geometry.TriangleMesh:
        """TSDF mesh (Open3D VoxelBlockGrid) of depth and colour rendered from the map at ``poses``
        (default: the retained views' poses), rendered at ``scale`` of the camera with the map's low-pass."""
        from .export import extract_triangle_mesh

        poses = [f.T_world_cam for f in self.views.views] if poses is None else list(poses)
        with torch.no_grad():
            return extract_triangle_mesh(lambda cam, T: self._render(cam, T, self.gmap.low_pass(cam)), poses,
                                         self.camera.scaled(scale), voxel_size=voxel_size, depth_max=depth_max, **kw)

    def __repr__(self) -> str:
        return (f"Reconstructor({self.camera.width}x{self.camera.height}, device={self.device}, renderer="
                f"{self.config.renderer}, gaussians={len(self.gmap)}, updates={self.stats.updates})")
