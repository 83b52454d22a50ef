"""Frame: one RGB-D observation with its camera, pose and timestamp, built from Open3D RGBD images."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import torch
import torch.nn.functional as F

from .camera import Camera, check_pose


DEPTH_MAX = 8.0  # metres: the one default range of measured depth (farther counts as no measurement)


class FrameError(ValueError):
    """A frame that cannot be used (bad size, dtype, pose, depth). The message names the frame and the field."""


@dataclass
class Frame:
    """One observation o_i = (I_i, D_i, K_i, T_wc_i, tau_i) of the paper, kept at source resolution on the CPU.

    color: [H, W, 3] float32 in [0, 1]; depth: [H, W] float32 metres, 0 = no measurement.
    """

    color: torch.Tensor
    depth: torch.Tensor
    camera: Camera
    T_world_cam: np.ndarray  # [4, 4] float64
    timestamp: float = 0.0
    index: int = 0
    _pyramid: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_rgbd(
        cls,
        rgbd,
        camera: Camera,
        T_world_cam,
        *,
        depth_scale: float = 1000.0,
        depth_max: float = DEPTH_MAX,
        timestamp: float = 0.0,
        index: int = 0,
    ) -> "Frame":
        """Wrap a legacy ``o3d.geometry.RGBDImage`` or tensor ``o3d.t.geometry.RGBDImage``.

        Integer depth is divided by ``depth_scale``; float depth is taken as metres. Colour may be uint8
        (0-255), uint16 (0-65535) or float in [0, 1]. Depth beyond ``depth_max`` becomes 0 (no measurement).
        """
        where = f"frame {index}"
        if isinstance(rgbd, o3d.t.geometry.RGBDImage):
            color = rgbd.color.as_tensor().cpu().numpy()
            depth = rgbd.depth.as_tensor().cpu().numpy()
        elif isinstance(rgbd, o3d.geometry.RGBDImage):
            color = np.asarray(rgbd.color)
            depth = np.asarray(rgbd.depth)
            # The legacy RGBDImage factory functions already scale depth to metres and colour to float.
        else:
            raise FrameError(f"{where}: expected an Open3D RGBDImage (legacy or tensor), got {type(rgbd).__name__}")
        return cls.from_arrays(color, depth, camera, T_world_cam, depth_scale=depth_scale, depth_max=depth_max,
                               timestamp=timestamp, index=index)

    @classmethod
    def from_arrays(cls, color: np.ndarray, depth: np.ndarray, camera: Camera, T_world_cam, *,
                    depth_scale: float = 1000.0, depth_max: float = DEPTH_MAX, timestamp: float = 0.0,
                    index: int = 0) -> "Frame":
        where = f"frame {index}"
        color, depth = np.asarray(color), np.asarray(depth)
        if depth.ndim == 3 and depth.shape[2] == 1:
            depth = depth[..., 0]
        if color.ndim == 2:
            color = np.repeat(color[..., None], 3, axis=2)
        if color.ndim != 3 or color.shape[2] not in (3, 4):
            raise FrameError(f"{where}: colour must be HxWx3, got shape {color.shape}")
        color = color[..., :3]
        if depth.ndim != 2:
            raise FrameError(f"{where}: depth must be HxW, got shape {depth.shape}")
        if color.shape[:2] != depth.shape:
            raise FrameError(f"{where}: colour {color.shape[1]}x{color.shape[0]} and depth "
                             f"{depth.shape[1]}x{depth.shape[0]} sizes differ")
        if (camera.height, camera.width) != depth.shape:
            raise FrameError(f"{where}: intrinsics are for {camera.width}x{camera.height} but the image is "
                             f"{depth.shape[1]}x{depth.shape[0]}")
        if color.dtype == np.uint8:
            color_f = color.astype(np.float32) / 255.0
        elif color.dtype == np.uint16:
            color_f = color.astype(np.float32) / 65535.0
        elif np.issubdtype(color.dtype, np.floating):
            color_f = color.astype(np.float32)
            if not np.all(np.isfinite(color_f)):
                raise FrameError(f"{where}: colour contains NaN or Inf")
            if color_f.max(initial=0.0) > 1.0 + 1e-3:
                raise FrameError(f"{where}: float colour must be in [0, 1], max is {color_f.max():.3g}")
        else:
            raise FrameError(f"{where}: unsupported colour dtype {color.dtype} (use uint8, uint16 or float)")
        if np.issubdtype(depth.dtype, np.integer):
            if depth_scale <= 0:
                raise FrameError(f"{where}: depth_scale must be positive, got {depth_scale}")
            depth_m = depth.astype(np.float32) / float(depth_scale)
        elif np.issubdtype(depth.dtype, np.floating):
            depth_m = depth.astype(np.float32)
            if np.isnan(depth_m).all():
                raise FrameError(f"{where}: depth is all NaN")
            depth_m = np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0)
        else:
            raise FrameError(f"{where}: unsupported depth dtype {depth.dtype} (use uint16 or float32 metres)")
        depth_m[(depth_m < 0) | (depth_m > depth_max)] = 0.0
        if not (depth_m > 0).any():
            raise FrameError(f"{where}: depth has no valid measurement (all zero, NaN or beyond depth_max={depth_max})")
        try:
            T = check_pose(T_world_cam, f"{where}: pose")
        except ValueError as e:
            raise FrameError(str(e)) from None
        return cls(torch.from_numpy(np.ascontiguousarray(color_f)), torch.from_numpy(np.ascontiguousarray(depth_m)),
                   camera, T, float(timestamp), int(index))

    def at_scale(self, scale: float, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor, Camera]:
        """Colour [h, w, 3], depth [h, w] and camera of this frame resampled by ``scale`` (cached).

        The source images stay intact: this is the supervision grid of Load-Adaptive Fidelity. Colour is
        area-averaged; depth keeps the nearest sample so that holes and edges do not blend.
        """
        key = (float(scale), str(device))
        hit = self._pyramid.get(key)
        if hit is not None:
            return hit
        cam = self.camera.scaled(scale)
        if cam.width == self.camera.width and cam.height == self.camera.height:
            color, depth = self.color, self.depth
        else:
            color = F.interpolate(self.color.permute(2, 0, 1)[None], size=(cam.height, cam.width), mode="area")[0]
            color = color.permute(1, 2, 0).contiguous()
            depth = F.interpolate(self.depth[None, None], size=(cam.height, cam.width), mode="nearest")[0, 0]
        out = (color.to(device), depth.to(device), cam)
        self._pyramid[key] = out
        return out

    def point_sampled(self, step: int, phase_x: int, phase_y: int, device: torch.device | str = "cpu"
                      ) -> tuple[torch.Tensor, torch.Tensor, Camera]:
        """Colour [h, w, 3], depth [h, w] and camera of every ``step``-th source pixel from column ``phase_x`` and
        row ``phase_y`` (not cached): as many pixels as :meth:`at_scale` at 1 / step when the size divides, but
        samples of the source image rather than averages (:mod:`..scheduling.supervision`)."""
        w, h = self.camera.width // step, self.camera.height // step
        rows = slice(phase_y, phase_y + step * h, step)
        cols = slice(phase_x, phase_x + step * w, step)
        color = self.color[rows, cols].contiguous().to(device)
        depth = self.depth[rows, cols].contiguous().to(device)
        c = self.camera
        return color, depth, Camera(w, h, c.fx / step, c.fy / step, (c.cx - phase_x) / step, (c.cy - phase_y) / step)

    def decoded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(colour [H, W, 3], depth [H, W]) float32: the images themselves (a held-out view stored compactly,
        :class:`~eligsir_o3d.eval.heldout_view.HeldoutView`, decodes them here)."""
        return self.color, self.depth

    def drop_cache(self) -> None:
        self._pyramid.clear()
