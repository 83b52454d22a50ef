"""Loop closure on a tracked trajectory, offline: ATE before and after, and every verified loop edge's error.

Replays a tracker's trajectory (a TUM file, e.g. from ``benchmarks/quality/poses.py --out DIR``) frame by frame
through :class:`eligsir_o3d.pose.loop_closure.LoopClosure` with the recording's depth, exactly as a mapping run
calls it (causal: a keyframe only sees the frames before it), then scores the corrected trajectory (every frame
carried by its keyframe's final correction) against the ground truth. Each verified candidate is printed with
its registration test and the error of its edge against the ground truth's relative pose, to tune the tests.

    python benchmarks/quality/poses.py --sources odometry kiss-icp --frames 1000 --out runs/poses
    python -m benchmarks.quality.loops runs/poses/kitchen_odometry.txt runs/poses/kitchen_kiss-icp.txt
    python -m benchmarks.quality.loops runs/poses/kitchen_odometry.txt --set min_fitness=0.5 --set radius=0.8
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from eligsir_o3d.core.camera import invert_pose, rotation_angle_deg
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose import plot_trajectories, read_tum_trajectory, trajectory_accuracy, write_tum_trajectory
from eligsir_o3d.pose.accuracy import associate_stamps
from eligsir_o3d.pose.loop_closure import LoopClosure, LoopClosureConfig, loop_closure_for
from eligsir_o3d.pose.loops import LoopConfig
from eligsir_o3d.pose.pose_graph import GraphConfig

ROOT = Path(__file__).resolve().parents[2]
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"


def _configs(sets: list[str]) -> tuple[LoopConfig, GraphConfig]:
    loops, graph = LoopConfig(), GraphConfig()
    for s in sets:
        key, value = s.split("=", 1)
        target = loops if key in {f.name for f in dataclasses.fields(LoopConfig)} else graph
        setattr(target, key, type(getattr(target, key))(value))
    return loops, graph


def replay(seq, stamps: np.ndarray, poses: list[np.ndarray], lc: LoopClosure, depth_cache: dict) -> list:
    """Run ``lc`` over the frames whose timestamps are ``stamps`` and finish it (its last keyframes settle);
    returns (frame index, timestamp, T_used)."""
    idx, _ = associate_stamps(np.asarray(seq.timestamps), stamps, 0.02)
    used = []
    for i, k in zip(idx, range(len(stamps))):
        depth = depth_cache.get(int(i))
        if depth is None:
            depth = seq.frame(int(i)).depth.numpy()
            depth_cache[int(i)] = depth
        T = lc.on_frame(int(i), poses[k], depth, seq.camera)
        used.append((int(i), float(stamps[k]), T))
    lc.finish()
    return used


def odometry_edge_errors(lc: LoopClosure, seq) -> dict:
    """Mean error of the graph's odometry edges (keyframe to keyframe) against the ground truth's relative poses:
    the tracker's relative motion, and the edge the graph used (refined where ``refine_edges`` is on)."""
    out = {}
    for name, rels in (("tracker", [invert_pose(a.raw_pose) @ b.raw_pose for a, b in zip(lc.keys, lc.keys[1:])]),
                       ("graph", lc.odo_rel[1:])):
        errs = []
        for a, b, T in zip(lc.keys, lc.keys[1:], rels):
            E = invert_pose(invert_pose(seq.poses[a.index]) @ seq.poses[b.index]) @ T
            errs.append((100 * np.linalg.norm(E[:3, 3]), rotation_angle_deg(E[:3, :3])))
        e = np.asarray(errs).reshape(-1, 2)
        out[f"edge_err_{name}_cm"], out[f"edge_err_{name}_deg"] = (float(x) for x in (e.mean(0) if len(e) else (0, 0)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trajectories", nargs="+", type=Path, help="TUM trajectories of a tracker on the sequence")
    ap.add_argument("--data", type=Path, default=KITCHEN)
    ap.add_argument("--set", action="append", default=[], help="LoopConfig/GraphConfig field=value")
    ap.add_argument("--out", type=Path, default=None, help="write the corrected trajectories (TUM) here")
    ap.add_argument("--edges", action="store_true", help="print every verified candidate")
    ap.add_argument("--source", default=None, help="the tracker's name (default: the file name after its first _)")
    args = ap.parse_args(argv)
    seq = open_sequence(args.data)
    gt = {float(t): T for t, T in zip(seq.timestamps, seq.poses)}
    cache: dict = {}
    for path in args.trajectories:
        stamps, poses = read_tum_trajectory(path)
        source = args.source or path.stem.split("_", 1)[-1]  # runs/poses/kitchen_kiss-icp.txt: kiss-icp
        detect, graph = _configs(args.set)
        lc = loop_closure_for(LoopClosureConfig(enabled="on", detect=detect, graph=graph), True, source)
        used = replay(seq, np.asarray(stamps), poses, lc, cache)
        final = [lc.pose_of(i, T) for i, _, T in used]
        ts = [t for _, t, _ in used]
        before = trajectory_accuracy((ts, [poses[k] for k in range(len(used))]), gt)
        online = trajectory_accuracy((ts, [T for _, _, T in used]), gt)
        after = trajectory_accuracy((ts, final), gt)
        row = {"trajectory": path.name, "min_fitness": lc.cfg.min_fitness, "frames": len(used),
               "ate_before_cm": 100 * before["ate_rmse_m"], "ate_online_cm": 100 * online["ate_rmse_m"],
               "ate_after_cm": 100 * after["ate_rmse_m"], **odometry_edge_errors(lc, seq), **lc.counters()}
        print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        if args.edges:
            for r in lc.log:
                G = invert_pose(seq.poses[r["with"]]) @ seq.poses[r["frame"]]
                E = invert_pose(G) @ np.asarray(r["transform"])
                print(f"  {r['frame']:4d}->{r['with']:4d} fit {r['fitness']:.3f} rmse {1000 * r['rmse_m']:.1f} mm "
                      f"shift {100 * r['shift_m']:.1f} cm {r['turn_deg']:.1f} deg  accepted {r['accepted']}  "
                      f"edge error vs gt {100 * np.linalg.norm(E[:3, 3]):.1f} cm "
                      f"{rotation_angle_deg(E[:3, :3]):.2f} deg")
        if args.out is not None:
            write_tum_trajectory(args.out / f"{path.stem}_loops.txt", ts, final)
            plot_trajectories(args.out / f"{path.stem}_loops.png",
                              {"gt": gt, "tracker": (ts, poses[:len(used)]), "loop-closed": (ts, final)},
                              reference="gt", title=f"{path.stem}: ATE {row['ate_before_cm']:.2f} -> "
                                                    f"{row['ate_after_cm']:.2f} cm (top view, aligned to gt)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
