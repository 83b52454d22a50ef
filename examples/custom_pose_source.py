"""Plug your own tracker in as a pose source: subclass PoseSource and implement ``_track``.

    python examples/custom_pose_source.py ../shared/data/7scenes_redkitchen_jpg1000 --frames 100

The example tracker is a frame-to-frame Open3D RGB-D odometry with a constant-velocity initial guess -- stand in
your own (a visual-inertial system, a robot's odometry, a motion-capture feed). The base class times every call,
validates the returned pose and counts lost frames; ``TrackingLost`` tells the caller to skip a frame.
"""

import argparse

import numpy as np
import open3d as o3d
import eligsir_o3d as eo3d
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose import PoseSource, TrackingLost, trajectory_accuracy


class ConstantVelocityOdometry(PoseSource):
    name = "constant-velocity odometry"

    def __init__(self, sequence=None, max_step_m: float = 0.2):
        super().__init__(sequence)
        self.max_step_m = max_step_m

    def _prepare(self, sequence):  # called once before the first frame: reset the state
        self.prev, self.T, self.velocity = None, None, np.eye(4)

    def _track(self, index, timestamp, color, depth, camera, gt_pose):
        """color [H, W, 3] float in [0, 1], depth [H, W] metres; return camera-to-world [4, 4]."""
        rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(color.numpy())),
                                        o3d.t.geometry.Image(o3d.core.Tensor(depth.numpy()[..., None])))
        if self.prev is None:  # first frame: the map's origin (or the ground truth when given, to compare)
            self.prev, self.T = rgbd, (np.eye(4) if gt_pose is None else gt_pose.copy())
            return self.T
        result = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
            rgbd, self.prev, o3d.core.Tensor(camera.K), o3d.core.Tensor(self.velocity), depth_scale=1.0,
            depth_max=4.0, criteria_list=[o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in (10, 5, 3)])
        T_prev_cur = result.transformation.numpy()       # maps current-camera points into the previous camera
        if result.fitness < 0.05 or np.linalg.norm(T_prev_cur[:3, 3]) > self.max_step_m:
            raise TrackingLost(f"frame {index}: odometry fitness {result.fitness:.2f}")
        self.velocity = T_prev_cur                       # next frame's initial guess: the same motion again
        self.T = self.T @ T_prev_cur                     # T_world_cur = T_world_prev @ T_prev_cur
        self.prev = rgbd
        return self.T


ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("sequence", nargs="?", default="../shared/data/7scenes_redkitchen_jpg1000")
ap.add_argument("--frames", type=int, default=100)
ap.add_argument("--updates", type=int, default=None)
ap.add_argument("--drain", type=int, default=None, help="updates after the last frame (default: the config's)")
args = ap.parse_args()

seq = open_sequence(args.sequence)
tracker = ConstantVelocityOdometry()
tracker.prepare(seq)
rec = eo3d.Reconstructor(seq.intrinsic, device="cpu", pose_source=tracker)  # integrate(rgbd, None) tracks
rec.config.depth_scale = seq.depth_scale
est, gt = {}, {}
for i in range(min(args.frames, len(seq))):
    frame = seq.frame(i)
    try:
        T = tracker.track(i, frame.timestamp, frame.color, frame.depth, frame.camera,
                          gt_pose=seq.poses[i] if seq.poses is not None and i == 0 else None)
    except TrackingLost as e:
        print(f"skipped: {e}")
        continue
    frame.T_world_cam = T
    rec.integrate(frame, updates=args.updates)
    est[frame.timestamp] = T
    if seq.poses is not None:
        gt[frame.timestamp] = seq.poses[i]
if args.drain is not None:
    rec.config.clock.drain_updates = args.drain
rec.finalize()
print(f"{tracker.name}: {tracker.frames_tracked} frames at {tracker.ms_per_frame:.0f} ms, {len(rec.gmap)} Gaussians")
if len(gt) >= 3:
    print(f"ATE against the sequence's poses: {100 * trajectory_accuracy(est, gt)['ate_rmse_m']:.2f} cm")
