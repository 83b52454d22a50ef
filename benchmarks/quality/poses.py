"""Pose-source benchmark: trajectory accuracy and tracking time of each source on real sequences.

- Online sources (Open3D RGB-D odometry frame-to-model and frame-to-frame, kiss-icp) on the first ``--frames``
  (300) frames of ``../shared/data/7scenes_redkitchen_jpg1000``: ATE RMSE (rigid Umeyama alignment), RPE per frame
  pair, ms per frame spent inside ``track`` (image reading excluded), lost frames.
- pycolmap SfM on the 50 frames of ``../shared/data/sun3d_mit76_studyroom_f0935``: ATE and wall time of ``prepare``.

The first frame is anchored at its ground-truth pose (``gt_pose`` on the first call), as the pipeline does; the
ATE is computed after alignment anyway. Each source runs in its own process order, one after the other, so the
times are comparable only on an otherwise idle machine: the 1-minute load average is printed with every row.

    python benchmarks/quality/poses.py                         # all sources, table
    python benchmarks/quality/poses.py --sources odometry kiss-icp --frames 100
    python benchmarks/quality/poses.py --sources colmap --out runs/poses   # also trajectories (TUM) and plots (PNG)
    python benchmarks/quality/poses.py --json
    python benchmarks/quality/poses.py --sources kiss-icp --frames 1000 --holdout-every 8 --out runs/poses875

``--holdout-every N`` tracks only the frames a mapping run tracks (``eligsir map``'s ``--holdout-every``: every
N-th frame, offset N // 2, is held out for evaluation and never reaches the tracker), so that
``benchmarks.quality.loops`` replays the very trajectory a mapping run's loop closure sees.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from eligsir_o3d.datasets import open_sequence  # noqa: E402
from eligsir_o3d.pose import TrackingLost, get_pose_source, plot_trajectories, trajectory_accuracy  # noqa: E402
from eligsir_o3d.pose import write_tum_trajectory  # noqa: E402
from eligsir_o3d.run.pipeline import heldout_indices  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
KITCHEN = DATA / "7scenes_redkitchen_jpg1000"
STUDYROOM = DATA / "sun3d_mit76_studyroom_f0935"

# name -> (spec, options)
SOURCES = {
    "odometry": ("odometry", {}),
    "odometry-f2f": ("odometry", {"mode": "frame", "scale": 1.0}),
    "kiss-icp": ("kiss-icp", {}),
    "colmap": ("colmap", {}),
    # variants, run only when named in --sources
    "odometry-fullres": ("odometry", {"scale": 1.0}),
    "odometry-raycast3": ("odometry", {"raycast_every": 3}),
    "odometry-f2f-half": ("odometry", {"mode": "frame", "scale": 0.5}),
    "kiss-icp-2cm": ("kiss-icp", {"voxel_size": 0.02, "max_points_per_voxel": 20, "max_iterations": 500,
                                  "convergence": 1e-4}),
}
DEFAULT = ["odometry", "odometry-f2f", "kiss-icp", "colmap"]


def tracked_frames(n: int, holdout_every: int = 0) -> list[int]:
    """The frame indices among the first ``n`` that a mapping run with ``--holdout-every holdout_every`` tracks
    (all of them for 0)."""
    held = set(heldout_indices(n, holdout_every)) if holdout_every else set()
    return [i for i in range(n) if i not in held]


def run_online(name: str, spec: str, options: dict, seq, n: int, holdout_every: int = 0) -> dict:
    src = get_pose_source(spec, sequence=seq, **options)
    src.prepare(seq)
    stamps, poses, lost = [], [], []
    frames = tracked_frames(n, holdout_every)
    for i in frames:
        frame = seq.frame(i)
        try:
            T = src.track(i, frame.timestamp, frame.color, frame.depth, frame.camera,
                          gt_pose=seq.poses[i] if i == frames[0] else None)
        except TrackingLost as e:
            lost.append(str(e))
            continue
        stamps.append(frame.timestamp)
        poses.append(T)
    acc = trajectory_accuracy((stamps, poses), (seq.timestamps[:n], seq.poses[:n]))
    extra = {k: getattr(src, k) for k in ("frames_on_previous", "lowest_fitness", "model_blocks") if hasattr(src, k)}
    return {"source": name, "sequence": seq.name, "frames": len(frames), "lost": len(lost), "first_lost": lost[:1],
            **extra,
            "ms_per_frame": src.ms_per_frame, "cpu_ms_per_frame": src.cpu_ms_per_frame, **{k: acc[k] for k in ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg")},
            "load1": os.getloadavg()[0], "_traj": (stamps, poses)}


def run_colmap(seq, options: dict) -> dict:
    src = get_pose_source("colmap", sequence=seq, **options)
    t0 = time.perf_counter()
    src.prepare(seq)
    wall = time.perf_counter() - t0
    stamps, poses = [], []
    for i in range(len(seq)):
        try:
            poses.append(src.track(i, float(seq.timestamps[i]), None, None, seq.camera))
            stamps.append(float(seq.timestamps[i]))
        except TrackingLost:
            pass
    acc = trajectory_accuracy((stamps, poses), (seq.timestamps, seq.poses))
    acc_s = trajectory_accuracy((stamps, poses), (seq.timestamps, seq.poses), with_scale=True)
    return {"source": "colmap", "sequence": seq.name, "frames": len(seq), "lost": len(seq) - len(poses),
            "wall_s": wall, "cpu_s": src.cpu_seconds, "metric_scale": src.metric_scale, "scale_vs_gt": acc_s["scale"],
            **{k: acc[k] for k in ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg")}, "load1": os.getloadavg()[0],
            "_traj": (stamps, poses)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sources", nargs="+", default=DEFAULT, choices=list(SOURCES))
    ap.add_argument("--frames", type=int, default=300, help="frames of the 7-Scenes kitchen for online sources")
    ap.add_argument("--holdout-every", type=int, default=0,
                    help="track only the frames a mapping run with this --holdout-every tracks (0: every frame)")
    ap.add_argument("--out", type=Path, default=None, help="write trajectories (TUM) and plots (PNG) here")
    ap.add_argument("--json", action="store_true", help="one JSON object per line")
    args = ap.parse_args(argv)

    rows, trajs = [], {}
    online = [s for s in args.sources if s != "colmap"]
    if online:
        kitchen = open_sequence(KITCHEN)
        n = min(args.frames, len(kitchen))
        trajs["kitchen"] = {"gt": (kitchen.timestamps[:n], kitchen.poses[:n])}
        for name in online:
            spec, options = SOURCES[name]
            rows.append(run_online(name, spec, options, kitchen, n, args.holdout_every))
            trajs["kitchen"][name] = rows[-1]["_traj"]
            report(rows[-1], args.json)
    if "colmap" in args.sources:
        room = open_sequence(STUDYROOM)
        rows.append(run_colmap(room, SOURCES["colmap"][1]))
        trajs["studyroom"] = {"gt": (room.timestamps, room.poses), "colmap": rows[-1]["_traj"]}
        report(rows[-1], args.json)
    if args.out is not None:
        for seq_name, named in trajs.items():
            for name, (stamps, poses) in named.items():
                write_tum_trajectory(args.out / f"{seq_name}_{name}.txt", stamps, poses)
            plot_trajectories(args.out / f"{seq_name}_trajectories.png", named, reference="gt",
                              title=f"{seq_name}: camera centres, top view (aligned to gt)")
        print(f"trajectories and plots in {args.out}")
    return 0


def report(row: dict, as_json: bool) -> None:
    row = {k: v for k, v in row.items() if not k.startswith("_")}
    if as_json:
        print(json.dumps(row))
        return
    timing = (f"{row['ms_per_frame']:6.1f} ms/frame (CPU {row['cpu_ms_per_frame']:.1f})" if "ms_per_frame" in row
              else f"{row['wall_s']:6.1f} s wall (CPU {row['cpu_s']:.1f} s), metric scale {row['metric_scale']:.4f}, "
                   f"scale vs gt {row['scale_vs_gt']:.3f}")
    print(f"{row['source']:13s} {row['sequence']:28s} {row['frames']:4d} frames  "
          f"ATE {100 * row['ate_rmse_m']:5.2f} cm  "
          f"RPE {1000 * row['rpe_trans_m']:5.2f} mm / {row['rpe_rot_deg']:.2f} deg  {timing}  lost {row['lost']}  "
          f"(load {row['load1']:.1f})", flush=True)
    if row.get("model_blocks"):
        print(f"    frames registered to the previous frame (model too thin): {row['frames_on_previous']}, "
              f"lowest fitness {row['lowest_fitness']:.2f}, TSDF blocks {row['model_blocks']}")
    if row.get("first_lost"):
        print(f"    first loss: {row['first_lost'][0]}")


if __name__ == "__main__":
    raise SystemExit(main())
