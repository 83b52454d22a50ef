"""Loop closure on a tracked trajectory, offline: ATE before and after, and every verified loop edge's error.

Replays a tracker's trajectory (a TUM file, e.g. from ``benchmarks/quality/poses.py --out DIR``) frame by frame
through :class:`eligsir_o3d.pose.loop_closure.LoopClosure` with the recording's depth, exactly as a mapping run
calls it (causal: a keyframe only sees the frames before it), then scores the corrected trajectory (every frame
carried by its keyframe's final correction) against the ground truth. Each verified candidate is printed with
its registration test and the error of its edge against the ground truth's relative pose, to tune the tests.

    python benchmarks/quality/poses.py --sources odometry kiss-icp --frames 1000 --out runs/poses
    python -m benchmarks.quality.loops runs/poses/kitchen_odometry.txt runs/poses/kitchen_kiss-icp.txt
    python -m benchmarks.quality.loops runs/poses/kitchen_odometry.txt --set min_fitness=0.5 --set radius=0.8
    python -m benchmarks.quality.loops runs/poses/kitchen_gt.txt --edge-report   # the graph's edges against gt
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


def graph_edges(lc: LoopClosure, gt_poses) -> list[dict]:
    """Every edge of ``lc``'s graph against the ground truth's relative pose (``gt_poses[frame index]``,
    camera-to-world): kind (``odometry``, ``skip`` (keyframe ``k - 2`` to ``k``), ``loop``, ``pruned`` loop),
    frame indices, error (cm, degrees), the information's correspondence count (its (5, 5) entry) and the
    Mahalanobis residual ``e' I e`` of the error (rotation first, as Open3D orders it)."""
    rows = [("odometry", lc.keys[k].index, lc.keys[k - 1].index, lc.odo_rel[k], lc.odo_info[k])
            for k in range(1, lc.settled)]
    rows += [("skip", lc.keys[e.source].index, lc.keys[e.target].index, e.transform, e.information)
             for e in getattr(lc, "skip_edges", [])]
    rows += [("pruned" if (e.source, e.target) in lc.pruned else "loop", lc.keys[e.source].index,
              lc.keys[e.target].index, e.transform, e.information) for e in lc.loop_edges]
    out = []
    for kind, s, t, T, info in rows:
        E = invert_pose(invert_pose(gt_poses[t]) @ gt_poses[s]) @ np.asarray(T)
        e = np.concatenate([_log_rotation(E[:3, :3]), E[:3, 3]])
        out.append({"kind": kind, "source": s, "target": t, "cm": 100 * float(np.linalg.norm(E[:3, 3])),
                    "deg": rotation_angle_deg(E[:3, :3]), "count": float(np.asarray(info)[5, 5]),
                    "chi2": float(e @ np.asarray(info) @ e)})
    return out


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, radians) of ``R``."""
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return w if angle < 1e-9 else w * angle / np.sin(angle)


def loop_pair_errors(lc: LoopClosure, gt_poses, reach: int = 2) -> list[tuple[float, float]]:
    """Two accepted loop edges that share one end and whose other ends are at most ``reach`` keyframes apart
    imply a short-range relative pose between those ends; its error against the ground truth (cm, degrees).
    Where these are small against the loops' own errors, neighbouring loops share their error (an offset between
    the two visits, in the registrations or in the ground truth) rather than each carrying its own noise."""
    loops = [(e.source, e.target, np.asarray(e.transform)) for e in lc.loop_edges
             if (e.source, e.target) not in lc.pruned]
    idx = [key.index for key in lc.keys]
    out = []
    for a, (s1, t1, L1) in enumerate(loops):
        for s2, t2, L2 in loops[a + 1:]:
            if t1 == t2 and s1 != s2 and abs(s1 - s2) <= reach:
                T, G = invert_pose(L1) @ L2, invert_pose(gt_poses[idx[s1]]) @ gt_poses[idx[s2]]
            elif s1 == s2 and t1 != t2 and abs(t1 - t2) <= reach:
                T, G = L1 @ invert_pose(L2), invert_pose(gt_poses[idx[t1]]) @ gt_poses[idx[t2]]
            else:
                continue
            E = invert_pose(G) @ T
            out.append((100 * float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])))
    return out


def edge_summary(lc: LoopClosure, gt_poses) -> dict:
    """Per kind of graph edge (:func:`graph_edges`): how many, the median error (cm, degrees), the median
    correspondence count and Mahalanobis residual; and the median error of :func:`loop_pair_errors`."""
    rows, out = graph_edges(lc, gt_poses), {}
    for kind in ("odometry", "skip", "loop", "pruned"):
        sel = [r for r in rows if r["kind"] == kind]
        if sel:
            out[kind] = {"edges": len(sel), **{f"median_{f}": float(np.median([r[f] for r in sel]))
                                                for f in ("cm", "deg", "count", "chi2")}}
    pairs = np.asarray(loop_pair_errors(lc, gt_poses)).reshape(-1, 2)
    if len(pairs):
        out["loop_pairs"] = {"pairs": len(pairs), "median_cm": float(np.median(pairs[:, 0])),
                             "median_deg": float(np.median(pairs[:, 1]))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trajectories", nargs="+", type=Path, help="TUM trajectories of a tracker on the sequence")
    ap.add_argument("--data", type=Path, default=KITCHEN)
    ap.add_argument("--set", action="append", default=[], help="LoopConfig/GraphConfig field=value")
    ap.add_argument("--out", type=Path, default=None, help="write the corrected trajectories (TUM) here")
    ap.add_argument("--edges", action="store_true", help="print every verified candidate")
    ap.add_argument("--edge-report", action="store_true",
                    help="print the graph's edges against the ground truth, per kind, and loop-pair consistency")
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
        if args.edge_report:
            for r in graph_edges(lc, seq.poses):
                print(f"  {r['kind']:8s} {r['source']:4d}->{r['target']:4d} error {r['cm']:5.2f} cm {r['deg']:5.2f} deg"
                      f"  count {r['count']:7.0f}  chi2 {r['chi2']:8.1f}")
            summary = edge_summary(lc, seq.poses)
            print(json.dumps({"edge_summary": {k: {f: round(v, 3) for f, v in d.items()} for k, d in summary.items()}}))
        if args.out is not None:
            write_tum_trajectory(args.out / f"{path.stem}_loops.txt", ts, final)
            plot_trajectories(args.out / f"{path.stem}_loops.png",
                              {"gt": gt, "tracker": (ts, poses[:len(used)]), "loop-closed": (ts, final)},
                              reference="gt", title=f"{path.stem}: ATE {row['ate_before_cm']:.2f} -> "
                                                    f"{row['ate_after_cm']:.2f} cm (top view, aligned to gt)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
