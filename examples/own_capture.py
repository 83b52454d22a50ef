"""Your own capture without poses: a plain folder of colour, depth and intrinsics, tracked by RGB-D odometry.

    my_capture/
      intrinsics.json   {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5,
                         "depth_scale": 1000.0}
      color/000000.jpg  colour (.png or .jpg)
      depth/000000.png  16-bit depth, 0 = no measurement

    python examples/own_capture.py my_capture --out runs/mine

Each frame is posed by a pose source before it is integrated: "odometry" is Open3D's RGB-D frame-to-model
tracking ("kiss-icp" works too with the pose extra installed). The map starts at the first frame's camera.
"""

import argparse
from pathlib import Path

import eligsir_o3d as eo3d
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose import TrackingLost, get_pose_source, write_tum_trajectory

ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("capture", type=Path)
ap.add_argument("--frames", type=int, default=None)
ap.add_argument("--updates", type=int, default=None, help="optimisation updates per frame (default: the config's)")
ap.add_argument("--drain", type=int, default=None, help="updates after the last frame (default: the config's)")
ap.add_argument("--out", type=Path, default=Path("runs/own_capture"))
args = ap.parse_args()

seq = open_sequence(args.capture)                      # detects the plain folder layout; no poses needed
tracker = get_pose_source("odometry")                  # Open3D RGB-D odometry, frame to model
rec = eo3d.Reconstructor(seq.intrinsic, device="cpu")
rec.config.depth_scale = seq.depth_scale
stamps, poses = [], []
for i in range(len(seq) if args.frames is None else min(args.frames, len(seq))):
    frame = seq.frame(i)                               # float colour, metric depth, placeholder pose
    try:
        frame.T_world_cam = tracker.track(i, frame.timestamp, frame.color, frame.depth, frame.camera)
    except TrackingLost as e:                          # odometry could not place this frame: skip it, go on
        print(f"skipped: {e}")
        continue
    rec.integrate(frame, updates=args.updates)         # a Frame carries its own pose and timestamp
    stamps.append(frame.timestamp)
    poses.append(frame.T_world_cam)
if args.drain is not None:
    rec.config.clock.drain_updates = args.drain
rec.finalize()

args.out.mkdir(parents=True, exist_ok=True)
rec.save_ply(args.out / "map.ply")
write_tum_trajectory(args.out / "trajectory.txt", stamps, poses)
print(f"tracked {tracker.frames_tracked} frames ({tracker.ms_per_frame:.0f} ms each), "
      f"{len(rec.gmap)} Gaussians; map in {args.out / 'map.ply'}")
