"""kiss-icp as a pose source: frame-to-map point-to-point ICP on points back-projected from depth.

KISS-ICP (Vizzo et al., RA-L 2023) is built for 360-degree LiDAR; these settings suit indoor RGB-D instead:
metres-scale ranges (0.1 to ``max_range`` = 5 m), a small voxel map (``voxel_size``), an adaptive threshold
started at 0.1 m with a 1 cm minimum motion, no deskewing (a depth image is one instant), and every ``stride``-th
pixel. Points stay in OpenCV camera axes (kiss-icp is axis-agnostic), so its pose, camera-to-first-frame, is
composed with the first frame's pose: ``T_world_cam = T_world_first @ last_pose``.

One registration step is kiss-icp's own ``KissICP.register_frame`` split in two, so that an estimate can be
checked (enough points, overlap with the map, plausible motion) before it touches the map and the motion model:
a rejected frame raises TrackingLost and leaves the state as it was.
"""

from __future__ import annotations

import numpy as np

from ..core.voxels import pack
from .base import PoseSource, TrackingLost, as_float_tensor, check_jump, first_pose


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:  # [N, 3] -> [N] int64
    return pack(np.floor(points / voxel).astype(np.int64))


class KissICPSource(PoseSource):
    """Frame-to-map ICP (kiss-icp) on depth points; needs ``pip install kiss-icp`` (extra ``pose``)."""

    name = "kiss-icp"
    drifts = True

    def __init__(self, *, voxel_size: float = 0.05, max_points_per_voxel: int = 5, stride: int = 4,
                 min_range: float = 0.1, max_range: float = 5.0, initial_threshold: float = 0.1,
                 min_motion_th: float = 0.01, max_iterations: int = 30, convergence: float = 1e-3,
                 min_points: int = 500, min_overlap: float = 0.3, max_speed: float = 2.0,
                 max_angular_speed_deg: float = 180.0, sequence=None) -> None:
        super().__init__(sequence)
        try:
            from kiss_icp.config import load_config
        except ImportError as e:
            raise ImportError("pose source 'kiss-icp' needs kiss-icp: pip install kiss-icp "
                              "(or pip install 'eligsir-o3d[pose]')") from e
        cfg = load_config(None)  # a bare KISSConfig() crashes when used; load_config fills the derived fields
        cfg.data.deskew = False
        cfg.data.min_range, cfg.data.max_range = float(min_range), float(max_range)
        cfg.mapping.voxel_size = float(voxel_size)
        cfg.mapping.max_points_per_voxel = int(max_points_per_voxel)
        cfg.adaptive_threshold.initial_threshold = float(initial_threshold)
        cfg.adaptive_threshold.min_motion_th = float(min_motion_th)
        cfg.registration.max_num_iterations = int(max_iterations)
        cfg.registration.convergence_criterion = float(convergence)
        self.config = cfg
        self.stride, self.min_points, self.min_overlap = int(stride), int(min_points), float(min_overlap)
        self.max_speed, self.max_angular_speed_deg = float(max_speed), float(max_angular_speed_deg)
        self._reset()

    def _reset(self) -> None:
        from kiss_icp.kiss_icp import KissICP

        self._icp = KissICP(self.config)
        self._T_world_first: np.ndarray | None = None
        self._last_stamp = 0.0

    def _prepare(self, sequence) -> None:
        self._reset()

    def _points(self, index: int, depth, camera) -> np.ndarray:
        d = as_float_tensor(depth, "depth", index)[:: self.stride, :: self.stride].numpy()
        v, u = np.nonzero((d > self.config.data.min_range) & (d < self.config.data.max_range))
        z = d[v, u].astype(np.float64)
        u = u * self.stride
        v = v * self.stride
        pts = camera.unproject(u, v, z)
        if len(pts) < self.min_points:
            raise TrackingLost(f"frame {index}: only {len(pts)} valid depth points in "
                               f"[{self.config.data.min_range:g}, {self.config.data.max_range:g}] m "
                               f"(need {self.min_points}); cannot track")
        return pts

    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        points = self._points(index, depth, camera)
        icp = self._icp
        if self._T_world_first is None:
            self._T_world_first = first_pose(gt_pose)
            _, frame_down = icp.voxelize(points)
            icp.local_map.update(frame_down, icp.last_pose)
            self._last_stamp = timestamp
            return self._T_world_first

        source, frame_down = icp.voxelize(points)
        sigma = icp.adaptive_threshold.get_threshold()
        guess = icp.last_pose @ icp.last_delta  # constant-velocity prediction
        new_pose = icp.registration.align_points_to_map(points=source, voxel_map=icp.local_map,
                                                        initial_guess=guess, max_correspondance_distance=3 * sigma,
                                                        kernel=sigma)
        self._check(index, timestamp, source, new_pose)
        icp.adaptive_threshold.update_model_deviation(np.linalg.inv(guess) @ new_pose)
        icp.local_map.update(frame_down, new_pose)
        icp.last_delta = np.linalg.inv(icp.last_pose) @ new_pose
        icp.last_pose = new_pose
        self._last_stamp = timestamp
        return self._T_world_first @ new_pose

    def _check(self, index: int, timestamp: float, source: np.ndarray, new_pose: np.ndarray) -> None:
        """Reject an estimate whose points mostly fall outside the map, or that moves implausibly fast."""
        vs = 2.0 * self.config.mapping.voxel_size  # twice the map voxel: points near a voxel face still count
        map_keys = np.unique(_voxel_keys(self._icp.local_map.point_cloud(), vs))
        moved = source @ new_pose[:3, :3].T + new_pose[:3, 3]
        overlap = float(np.isin(_voxel_keys(moved, vs), map_keys).mean())
        if overlap < self.min_overlap:
            raise TrackingLost(f"frame {index}: kiss-icp alignment puts only {overlap:.0%} of the frame's points "
                               f"in mapped voxels (need {self.min_overlap:.0%}): the view does not overlap the map")
        check_jump(index, self._icp.last_pose, new_pose, timestamp - self._last_stamp, max_speed=self.max_speed,
                   max_angular_speed_deg=self.max_angular_speed_deg, name="kiss-icp")
