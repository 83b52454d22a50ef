"""The synthetic room's one loop for the loop-closure tests: 48 frames at 160x120, walked once and then
:data:`N` - :data:`LOOP` frames more along its start, tracked by a stand-in whose error grows along the path."""

import numpy as np

from eligsir_o3d.core.camera import invert_pose, rotation_angle_deg
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose.loops import LoopConfig

LOOP, N = 48, 50  # frames of one loop, frames walked


def rot(axis, deg):
    """A rotation by ``deg`` degrees about the unit ``axis`` as a 4x4 transform."""
    a = np.radians(deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    return T


def make_room():
    """(sequence, depths [N], true poses [N]) of the walk."""
    seq = open_sequence("synthetic", n_frames=LOOP, width=160, height=120)
    depths = [seq.frame(i).depth.numpy() for i in range(LOOP)]
    return seq, [depths[i % LOOP] for i in range(N)], [seq.poses[i % LOOP] for i in range(N)]


def drifted(poses):
    """A tracker's poses: the true relative motions, each with a small rotation and translation error."""
    E = rot(np.array([0.0, 1.0, 0.0]), 0.05)
    E[:3, 3] = [0.0005, 0.0, 0.0]
    out = [poses[0].copy()]
    for k in range(1, len(poses)):
        out.append(out[-1] @ invert_pose(poses[k - 1]) @ poses[k] @ E)
    return out


def loop_config():
    """Every frame a keyframe; loops from 30 frames back; keyframes settle at once (``settle_frames`` 0: the loop
    at the walk's end closes before it ends)."""
    return LoopConfig(keyframe_dist=0.0, cloud_stride=2, min_gap=30, radius=0.6, max_candidates=2, per_frame=2,
                      local=1, settle_frames=0)


def pose_error(A, B):
    """(metres, degrees) between two poses."""
    E = invert_pose(A) @ B
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])


class DriftingSource:
    """A tracker stand-in: the drifted poses of the walk, by frame index (``drifts``: loop closure is on)."""

    name, causal, drifts = "drifting", True, True

    def __init__(self, poses):
        self.poses = poses

    def track(self, index, timestamp, color, depth, camera, gt_pose=None):
        return self.poses[index]
