"""A RealSense or ROS bag (or a ScanNet .sens) to a Gaussian map (3DGS PLY) and a triangle mesh.

    python examples/bag_to_ply.py capture.bag --out runs/bag
    python examples/bag_to_ply.py my_ros2_bag/ --rgb-topic /cam/color/image_raw --pose-topic /cam/pose

Poses come from the bag's pose topic (or tf, with --pose-frames world:camera_color_optical_frame) when it has
one, else from Open3D RGB-D odometry. eligsir map does the same with held-out evaluation on top.
"""

import argparse
from pathlib import Path

import open3d as o3d

import eligsir_o3d as eo3d
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose import TrackingLost, get_pose_source

ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("bag")
ap.add_argument("--out", type=Path, default=Path("runs/bag"))
ap.add_argument("--frames", type=int, default=None)
ap.add_argument("--updates", type=int, default=None, help="optimisation updates per frame (default: the config's)")
ap.add_argument("--drain", type=int, default=None, help="updates after the last frame (default: the config's)")
for topic in ("rgb-topic", "depth-topic", "pose-topic", "pose-frames"):
    ap.add_argument(f"--{topic}", default=None)
args = ap.parse_args()

# Topic options only matter for ROS bags; the reader finds unambiguous topics by itself.
options = {k: v for k, v in vars(args).items() if k in ("rgb_topic", "depth_topic", "pose_topic", "pose_frames")
           and v is not None}
seq = open_sequence(args.bag, **options)
print(seq)
tracker = None if seq.poses is not None else get_pose_source("odometry")  # no poses in the bag: track
rec = eo3d.Reconstructor(seq.intrinsic, device="cpu")
rec.config.depth_scale = seq.depth_scale
poses = []
for i in range(len(seq) if args.frames is None else min(args.frames, len(seq))):
    frame = seq.frame(i)                                   # reads only this frame's messages from the bag
    if tracker is not None:
        try:
            frame.T_world_cam = tracker.track(i, frame.timestamp, frame.color, frame.depth, frame.camera)
        except TrackingLost as e:
            print(f"skipped: {e}")
            continue
    rec.integrate(frame, updates=args.updates)
    poses.append(frame.T_world_cam)
if args.drain is not None:
    rec.config.clock.drain_updates = args.drain
rec.finalize()

args.out.mkdir(parents=True, exist_ok=True)
rec.save_ply(args.out / "map.ply")
mesh = rec.extract_triangle_mesh(poses[::max(1, len(poses) // 100)], voxel_size=0.02)  # TSDF fusion of
# depth rendered from the map at (up to 100 of) the recording's poses
o3d.io.write_triangle_mesh(str(args.out / "mesh.ply"), mesh)
print(f"{len(rec.gmap)} Gaussians -> {args.out / 'map.ply'}; mesh with {len(mesh.triangles)} triangles -> {args.out / 'mesh.ply'}")
