"""The README's Python loop: feed RGB-D frames with their poses to a Reconstructor, then save the map.

    python examples/integrate_loop.py ../shared/data/7scenes_redkitchen_jpg1000 --frames 200 --out runs/loop

Any layout open_sequence knows works as SEQUENCE (TUM, Replica, a plain folder, a ROS or RealSense bag, a
ScanNet .sens); the sequence must carry poses (see own_capture.py for one without).
"""

import argparse
from pathlib import Path

import eligsir_o3d as eo3d
from eligsir_o3d.datasets import open_sequence

ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("sequence", nargs="?", default="../shared/data/7scenes_redkitchen_jpg1000")
ap.add_argument("--frames", type=int, default=200, help="how many frames to integrate")
ap.add_argument("--updates", type=int, default=None, help="optimisation updates per frame (default: the config's)")
ap.add_argument("--drain", type=int, default=None, help="updates after the last frame (default: the config's)")
ap.add_argument("--out", type=Path, default=Path("runs/loop"))
args = ap.parse_args()

seq = open_sequence(args.sequence)
print(seq)
rec = eo3d.Reconstructor(seq.intrinsic, device="cpu")      # "cuda:0" on a GPU machine
rec.config.depth_scale = seq.depth_scale                   # integer depth / depth_scale = metres
for i in range(min(args.frames, len(seq))):
    item = seq[i]                                          # o3d.t.geometry.RGBDImage + camera-to-world pose
    rec.integrate(item.rgbd, item.T_world_cam, timestamp=item.timestamp, updates=args.updates)
if args.drain is not None:
    rec.config.clock.drain_updates = args.drain
rec.finalize()                                             # a bounded drain: the map as the stream ends

args.out.mkdir(parents=True, exist_ok=True)
rec.save_ply(args.out / "map.ply")                         # a standard 3DGS PLY (any 3DGS viewer opens it)
view = rec.render(seq[0].T_world_cam)                      # colour [H, W, 3], depth [H, W] metres, alpha [H, W]
print(f"{len(rec.gmap)} Gaussians, {rec.stats.updates} updates; rendered frame 0: "
      f"mean depth {float(view.depth[view.alpha > 0.5].mean()):.2f} m; map in {args.out / 'map.ply'}")
