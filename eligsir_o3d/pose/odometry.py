"""Open3D RGB-D odometry as a pose source, frame-to-model by default.

``mode="model"`` (default) is the KinectFusion scheme that Open3D's dense SLAM uses: the tracked frames are fused
into a small TSDF (``o3d.t.geometry.VoxelBlockGrid``, depth only), the TSDF is ray-cast at the previous pose,
and the new frame is registered to that synthetic depth map with multi-scale point-to-plane RGB-D odometry
(``o3d.t.pipelines.odometry.rgbd_odometry_multi_scale``). Registering to the fused model instead of the last
noisy frame removes most of the drift of frame-to-frame odometry. Tracking runs at ``scale`` (0.5: 320 x 240 for
VGA input), which measured both faster and more accurate than full resolution. Where the model sees too little
(the camera turned toward unmapped space), the frame is registered to the previous frame instead.

``mode="frame"`` is plain frame-to-frame odometry (Hybrid: photometric + geometric), kept for comparison.

First 300 frames of 7scenes_redkitchen_jpg1000, 2-core CPU, ``python benchmarks/quality/poses.py`` (ATE after rigid
alignment / RPE per frame pair / wall ms per frame at load ~2):

==========================================================  =======  =======  ========
variant                                                      ATE cm   RPE mm   ms/frame
==========================================================  =======  =======  ========
frame-to-model, point-to-plane, 320x240 (default)            2.55     3.08     37
  same, ray-cast every 3rd frame (``raycast_every=3``)       2.52     3.13     23
  same, without the half-voxel ray-cast correction           2.25     3.49     -
  same, 640x480                                              3.08     3.10     100
  same, 3 cm voxels (before the correction)                  2.71-2.97  3.8-4.1  -
  same, Hybrid (photometric + geometric) against the model   6.96     10.2     -
frame-to-frame Hybrid 640x480, iterations 20/10/5            2.70     5.07     69
  same, iterations 10/5/3 (the issue's 4.9 cm baseline)      4.86     5.14     -
  same, 320x240                                              2.83     5.40     26
frame-to-frame point-to-plane 640x480                        13.1     3.80     -
keyframes (new one past 10-20 cm / 10-15 deg), 320x240       3.3-4.1  5.3-5.9  -
==========================================================  =======  =======  ========

The ground truth here is KinectFusion's own tracking: ATE differences under ~0.5 cm are within its accuracy;
the RPE (frame-to-frame drift) shows frame-to-model's gain more clearly.

Conventions: ``rgbd_odometry_multi_scale(source=current, target=reference)`` returns the transform taking
current-camera points into the reference camera, so ``T_world_cur = T_world_ref @ result``. Open3D's
``extrinsic`` arguments (integrate, ray_cast) are world-to-camera: ``inv(T_world_cam)``.
"""

from __future__ import annotations

import re

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch
import torch.nn.functional as F

from ..core.camera import Camera, invert_pose
from .base import PoseSource, TrackingLost, as_float_tensor, check_jump, first_pose, orthonormalize

_METHODS = {"point_to_plane": "PointToPlane", "hybrid": "Hybrid", "intensity": "Intensity"}


def downsample(color: torch.Tensor | None, depth: torch.Tensor, factor: int, edge_m: float = 0.05
               ) -> tuple[torch.Tensor | None, torch.Tensor]:
    """Block-average colour [H, W, 3] and depth [H, W] (float32 torch) by an integer ``factor``.

    Depth is the mean of the valid samples of each block, and 0 where the block straddles a depth edge
    (spread > ``edge_m``) or has no valid sample, so that no depth is invented between two surfaces. The
    block centre ((u' + 0.5) f - 0.5) matches :meth:`Camera.scaled`.
    """
    if factor == 1:
        return color, depth
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    d = depth[: h * factor, : w * factor].reshape(h, factor, w, factor).permute(0, 2, 1, 3).reshape(h, w, -1)
    valid = d > 0
    n = valid.sum(-1)
    mean = d.sum(-1) / n.clamp(min=1)
    spread = d.amax(-1) - torch.where(valid, d, torch.full_like(d, float("inf"))).amin(-1)
    mean[(n == 0) | (spread > edge_m)] = 0.0
    if color is not None:
        c = color[: h * factor, : w * factor].permute(2, 0, 1)[None]
        color = F.avg_pool2d(c, factor)[0].permute(1, 2, 0).contiguous()
    return color, mean.contiguous()


class OdometrySource(PoseSource):
    """Open3D multi-scale RGB-D odometry, frame-to-model (``mode="model"``) or frame-to-frame (``"frame"``).

    Options: ``scale`` tracking resolution (0.5); ``iterations`` per pyramid level, coarsest first; ``method``
    ``point_to_plane`` (default for model) or ``hybrid`` (default for frame); ``depth_min``/``depth_max``
    (m) of the depth used; ``voxel_size`` (m), ``trunc_voxels`` and ``max_blocks`` of the TSDF model (blocks of
    8^3 voxels farther than ``keep_radius`` m from the camera are dropped past ``max_blocks``); loss checks:
    ``min_valid_fraction`` of pixels with depth, ``min_fitness`` (inlier fraction of the registration),
    ``max_speed`` (m/s) and ``max_angular_speed_deg`` (deg/s).
    """

    name = "odometry"
    drifts = True

    def __init__(self, *, mode: str = "model", method: str | None = None, scale: float = 0.5,
                 iterations: tuple[int, ...] = (20, 10, 5), depth_min: float = 0.1, depth_max: float = 4.0,
                 voxel_size: float = 0.02, trunc_voxels: float = 4.0, max_blocks: int = 40000,
                 keep_radius: float = 5.0, raycast_every: int = 1, min_model_fraction: float = 0.15,
                 min_valid_fraction: float = 0.05, min_fitness: float = 0.1, max_speed: float = 2.0,
                 max_angular_speed_deg: float = 180.0, sequence=None) -> None:
        super().__init__(sequence)
        if mode not in ("model", "frame"):
            raise ValueError(f"odometry mode must be 'model' (frame-to-model) or 'frame' (frame-to-frame), "
                             f"got {mode!r}")
        method = method or ("point_to_plane" if mode == "model" else "hybrid")
        if method not in _METHODS:
            raise ValueError(f"odometry method must be one of {', '.join(_METHODS)}, got {method!r}")
        factor = 1.0 / float(scale)
        if abs(factor - round(factor)) > 1e-6 or round(factor) < 1:
            raise ValueError(f"odometry scale must be 1/n for an integer n (1, 0.5, 0.25...), got {scale}")
        self.mode, self.method_name, self.factor = mode, method, int(round(factor))
        self.name = "odometry" if mode == "model" else "odometry-f2f"
        self._method = getattr(o3d.t.pipelines.odometry.Method, _METHODS[method])
        self._criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(int(n)) for n in iterations]
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self.voxel_size, self.trunc_voxels = float(voxel_size), float(trunc_voxels)
        self.max_blocks, self.keep_radius = int(max_blocks), float(keep_radius)
        self.raycast_every = max(1, int(raycast_every))
        # Open3D 0.20's VoxelBlockGrid.ray_cast places surfaces half a voxel off from where integrate() put them
        # (a single fused synthetic frame ray-cast at its own pose: median depth error -9 to +18 mm at 2 cm voxels,
        # depending on the view; 0.3-1.8 mm after this shift; extract_point_cloud/mesh are unbiased). Ray-casting
        # with the world shifted by -voxel/2 on every axis undoes it. tests/pose/test_pose.py checks it.
        self._raycast_shift = np.eye(4)
        self._raycast_shift[:3, 3] = -0.5 * self.voxel_size
        self.min_model_fraction, self.min_valid_fraction = float(min_model_fraction), float(min_valid_fraction)
        self.min_fitness = float(min_fitness)
        self.max_speed, self.max_angular_speed_deg = float(max_speed), float(max_angular_speed_deg)
        self.last_fitness = float("nan")
        self.lowest_fitness = float("inf")  # over accepted and rejected frames, for tuning min_fitness
        self.frames_on_model = self.frames_on_previous = 0
        self._reset()

    # -- state ----------------------------------------------------------------------------------------------
    def _reset(self) -> None:
        self._vbg = None
        self._blocks = None  # block coordinates touched by the last integrated frame
        self._n_integrated = 0
        self._prev: tuple[o3d.t.geometry.RGBDImage, np.ndarray, float] | None = None  # (rgbd, T_world_cam, t)
        self._model: tuple[o3d.t.geometry.Image, np.ndarray] | None = None  # (ray-cast depth, its pose)
        self._model_age = 0

    def _prepare(self, sequence) -> None:
        self._reset()

    def _new_grid(self) -> o3d.t.geometry.VoxelBlockGrid:
        return o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)),
                                             self.voxel_size, 8, 20000, o3c.Device("CPU:0"))

    # -- one frame -------------------------------------------------------------------------------------------
    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        rgbd, cam = self._input(index, color, depth, camera)
        K = o3c.Tensor(cam.K)
        if self._prev is None:
            T = first_pose(gt_pose)
            self._accept(rgbd, K, T, timestamp)
            return T

        prev_rgbd, T_prev, t_prev = self._prev
        target, T_target = prev_rgbd, T_prev
        if self.mode == "model":
            if self._model is None or self._model_age >= self.raycast_every:
                depth_model = self._raycast(K, cam, T_prev)
                self._model = None if depth_model is None else (depth_model, T_prev)
                self._model_age = 0
            if self._model is not None:
                target = o3d.t.geometry.RGBDImage(rgbd.color, self._model[0])
                T_target = self._model[1]
                self._model_age += 1
        on_model = target is not prev_rgbd
        init = invert_pose(T_target) @ T_prev
        try:
            result = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                rgbd, target, K, o3c.Tensor(init), 1.0, self.depth_max, self._criteria, self._method)
        except RuntimeError as e:  # Open3D raises on a singular system (no usable correspondences)
            reason = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip().rsplit(": ", 1)[-1]
            raise TrackingLost(f"frame {index}: RGB-D odometry failed ({reason[:120]}): no usable "
                               f"correspondences with the {'model' if on_model else 'previous frame'}") from None
        self.last_fitness = float(result.fitness)
        self.lowest_fitness = min(self.lowest_fitness, self.last_fitness)
        if not result.fitness >= self.min_fitness:
            raise TrackingLost(f"frame {index}: RGB-D odometry fitness {result.fitness:.3f} below {self.min_fitness:g} "
                               f"(too few pixels agree with the {'model' if on_model else 'previous frame'})")
        T = orthonormalize(T_target @ result.transformation.numpy())
        check_jump(index, T_prev, T, timestamp - t_prev, max_speed=self.max_speed,
                   max_angular_speed_deg=self.max_angular_speed_deg, name="RGB-D odometry")
        if on_model:
            self.frames_on_model += 1
        else:
            self.frames_on_previous += 1
        self._accept(rgbd, K, T, timestamp)
        return T

    def _input(self, index: int, color, depth, camera: Camera) -> tuple[o3d.t.geometry.RGBDImage, Camera]:
        d = as_float_tensor(depth, "depth", index)
        if tuple(d.shape) != (camera.height, camera.width):
            raise ValueError(f"frame {index}: depth is {d.shape[1]}x{d.shape[0]} but the camera is "
                             f"{camera.width}x{camera.height}")
        # Point-to-plane ignores colour: skip it (and accept depth-only input).
        c = as_float_tensor(color, "colour", index) if color is not None and self.method_name != "point_to_plane" \
            else None
        d = torch.where((d >= self.depth_min) & (d <= self.depth_max), d, torch.zeros_like(d))
        c, d = downsample(c, d, self.factor)
        h, w = d.shape
        cam = camera.scaled(1.0 / self.factor) if self.factor > 1 else camera
        if (cam.height, cam.width) != (h, w):  # odd sizes: the block grid drops the last row/column
            cam = Camera(w, h, cam.fx, cam.fy, cam.cx, cam.cy)
        frac = float((d > 0).float().mean())
        if frac < self.min_valid_fraction:
            raise TrackingLost(f"frame {index}: only {frac:.1%} of pixels have depth in [{self.depth_min:g}, "
                               f"{self.depth_max:g}] m (need {self.min_valid_fraction:.0%}); cannot track")
        if c is None:
            c = torch.zeros((h, w, 3), dtype=torch.float32)
        rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3c.Tensor(c.numpy())),
                                        o3d.t.geometry.Image(o3c.Tensor(d[..., None].numpy())))
        return rgbd, cam

    def _accept(self, rgbd: o3d.t.geometry.RGBDImage, K: o3c.Tensor, T: np.ndarray, timestamp: float) -> None:
        """Make the frame the reference for the next one and (frame-to-model) fuse it into the TSDF."""
        self._prev = (rgbd, T, timestamp)
        if self.mode != "model":
            return
        if self._vbg is None:
            self._vbg = self._new_grid()
        extrinsic = o3c.Tensor(invert_pose(T))
        trunc = self.trunc_voxels
        blocks = self._vbg.compute_unique_block_coordinates(rgbd.depth, K, extrinsic, 1.0, self.depth_max, trunc)
        self._vbg.integrate(blocks, rgbd.depth, K, extrinsic, 1.0, self.depth_max, trunc)
        self._blocks = blocks
        self._n_integrated += 1
        self._prune(T)

    def _raycast(self, K, cam: Camera, T: np.ndarray) -> o3d.t.geometry.Image | None:
        """Depth of the TSDF model seen from ``T`` (None where it covers too little of the view)."""
        extrinsic = invert_pose(T) @ self._raycast_shift
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):  # range-map realloc notes
            out = self._vbg.ray_cast(self._blocks, K, o3c.Tensor(extrinsic), cam.width, cam.height, ["depth"],
                                     1.0, self.depth_min, self.depth_max, min(float(self._n_integrated), 3.0),
                                     self.trunc_voxels, 8)
        depth = out["depth"]
        if float((depth.numpy() > 0).mean()) < self.min_model_fraction:
            return None
        return o3d.t.geometry.Image(depth)

    def _prune(self, T: np.ndarray) -> None:
        """Keep the model small: past ``max_blocks`` blocks, drop those far from the camera."""
        hashmap = self._vbg.hashmap()
        if hashmap.size() <= self.max_blocks:
            return
        keys = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)]
        centres = (keys.numpy().astype(np.float64) + 0.5) * self.voxel_size * 8
        far = np.linalg.norm(centres - T[:3, 3], axis=1) > self.keep_radius
        if far.any():
            gone = o3c.Tensor(keys.numpy()[far])
            # Open3D's hash map hands an erased block's buffer slot to the next block it activates without
            # clearing it: zero the slots first, or a new block starts with a far block's distances and weights.
            slots = hashmap.find(gone)[0].to(o3c.int64)
            for name in ("tsdf", "weight"):
                values = self._vbg.attribute(name)
                values[slots] = o3c.Tensor.zeros((len(slots),) + tuple(values.shape[1:]), values.dtype)
            hashmap.erase(gone)

    @property
    def model_blocks(self) -> int:
        """Blocks (8^3 voxels) in the TSDF model."""
        return 0 if self._vbg is None else int(self._vbg.hashmap().size())
