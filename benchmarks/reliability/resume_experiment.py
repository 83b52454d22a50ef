"""Resume experiment (issue 6): a mapping process killed with SIGKILL mid-sequence resumes from its last
checkpoint and must finish like an uninterrupted run; then the mesh and point cloud of the map, and a PNG of the mesh.

    python benchmarks/reliability/resume_experiment.py --data ../shared/data/7scenes_redkitchen_jpg1000 --frames 300 \
        --out runs/resume_7scenes [--updates 4] [--every 50] [--kill-at 170]

Three processes map the same source frames (every 8th frame, offset 4, held out) with the deterministic budget
(``--updates`` per frame, fidelity driven by the cost model): a reference run, a run checkpointing every
``--every`` source frames that is SIGKILLed right after source frame ``--kill-at`` (mid-computation, not at a
checkpoint), and its resumption. Writes results.json, summary.md, the maps, mesh.ply, cloud.ply and mesh_*.png.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


# ---- one mapping process ------------------------------------------------------------------------------------
def child(args) -> None:
    import torch

    import eligsir_o3d as eo3d
    from eligsir_o3d.core.camera import pose_to_tum
    from eligsir_o3d.io.checkpoint import read_checkpoint, save_checkpoint
    from eligsir_o3d.budget import CostModel
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.eval.metrics import depth_rmse, psnr
    from eligsir_o3d.budget.memory import peak_rss_mb

    out = Path(args.run_dir)
    out.mkdir(parents=True, exist_ok=True)
    seq = open_sequence(args.data)
    n = min(len(seq), args.frames)
    held = [i for i in range(n) if i % 8 == 4]
    source = [i for i in range(n) if i % 8 != 4]
    cost = CostModel()
    t_start = time.perf_counter()
    if args.resume:
        ck = read_checkpoint(args.ck, sequence=seq)
        rec = eo3d.Reconstructor.from_checkpoint(ck)
        pos = int(ck["extra"]["pos"])
        saves = []  # this process's own saves
        print(f"resumed at source position {pos} (frame {source[pos]}) in {time.perf_counter() - t_start:.2f} s",
              flush=True)
    else:
        cfg = eo3d.Config(seed=0)
        cfg.depth_scale = seq.depth_scale
        rec = eo3d.Reconstructor(seq.intrinsic, "cpu", cfg)
        pos, saves = 0, []
    rec.set_load(0, seq.frame_period_s, cost)  # as BudgetClock does
    for k in range(pos, len(source)):
        rec.integrate(seq.frame(source[k], depth_max=rec.config.depth_max), updates=args.updates)
        print(f"frame {source[k]} pos {k + 1}", flush=True)
        if args.every and (k + 1) % args.every == 0:
            t0 = time.perf_counter()
            p = save_checkpoint(rec, args.ck, sequence=seq, extra={"pos": k + 1})
            saves.append({"pos": k + 1, "seconds": time.perf_counter() - t0, "bytes": p.stat().st_size})
            print(f"checkpoint pos {k + 1}", flush=True)
    rec.finalize()
    scores, rmses = [], []
    for i in held:
        f = seq.frame(i, depth_max=rec.config.depth_max)
        r = rec.render(f.T_world_cam)
        scores.append(psnr(r.color, f.color))
        rmses.append(depth_rmse(r.depth, f.depth))
    rec.save_ply(out / "map.ply")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for i in source:
        t, q = pose_to_tum(seq.poses[i])
        lines.append(f"{seq.timestamps[i]:.6f} " + " ".join(f"{x:.7f}" for x in (*t, *q)))
    (out / "trajectory.txt").write_text("\n".join(lines) + "\n")
    c = seq.camera
    (out / "config.json").write_text(json.dumps({**rec.config.to_dict(), "camera": vars(c)}, indent=1))
    result = {"frames_released": rec.stats.frames_released, "updates": rec.stats.updates,
              "gaussians": len(rec.gmap), "heldout_psnr": float(np.mean(scores)),
              "heldout_depth_rmse_m": float(np.nanmean(rmses)), "process_s": time.perf_counter() - t_start,
              "checkpoints": saves, "peak_rss_mb": peak_rss_mb()}
    torch.save({k: v.detach() for k, v in rec.gmap.params.items()}, out / "params.pt")
    (out / "result.json").write_text(json.dumps(result, indent=1))
    print("done", json.dumps(result), flush=True)


# ---- the experiment -----------------------------------------------------------------------------------------
def _spawn(args, run_dir: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, __file__, "--child", "--data", args.data, "--frames", str(args.frames), "--updates",
           str(args.updates), "--run-dir", str(run_dir), "--ck", str(args.out / "checkpoint.pt"), *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _finish(proc: subprocess.Popen, log: Path) -> None:
    text = proc.communicate()[0]
    log.write_text(text)
    if proc.returncode != 0:
        raise SystemExit(f"{log}: exited with {proc.returncode}\n{text[-2000:]}")


def render_mesh_png(mesh_path: Path, png: Path, T_world_cam: np.ndarray, camera) -> None:
    """Ray-cast the mesh (vertex colours, headlight Lambert shading) from ``T_world_cam``: no display needed."""
    import open3d as o3d

    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(mesh_path)))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    dirs = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    dirs = dirs @ T_world_cam[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_world_cam[:3, 3], dirs.shape), dirs], -1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    ok = np.isfinite(hit["t_hit"].numpy())
    tri = mesh.triangle.indices.numpy()[np.where(ok, hit["primitive_ids"].numpy(), 0)]
    uv = hit["primitive_uvs"].numpy()
    w = np.stack([1 - uv[..., 0] - uv[..., 1], uv[..., 0], uv[..., 1]], -1)
    colors = mesh.vertex.colors.numpy()
    rgb = (colors[tri] * w[..., None]).sum(-2)
    n = hit["primitive_normals"].numpy()
    d = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    shade = 0.35 + 0.65 * np.abs((n * d).sum(-1))
    img = np.where(ok[..., None], np.clip(rgb * shade[..., None], 0, 1), 1.0)
    o3d.t.io.write_image(str(png), o3d.t.geometry.Image(o3d.core.Tensor((img * 255).astype(np.uint8))))


def geometry_vs_sensor(data: str, frames: int, mesh_path: Path, cloud_path: Path) -> dict:
    """Distances (m) between the exported geometry and the held-out frames' sensor depth, back-projected."""
    import open3d as o3d

    from eligsir_o3d.datasets import open_sequence

    seq = open_sequence(data)
    pts = []
    for i in (i for i in range(min(len(seq), frames)) if i % 8 == 4):
        f = seq.frame(i, depth_max=4.0)
        p, _ = f.camera.backproject(f.depth, stride=4)
        pts.append(p.numpy() @ f.T_world_cam[:3, :3].T + f.T_world_cam[:3, 3])
    sensor = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts))).voxel_down_sample(0.01)
    mesh_pts = o3d.io.read_triangle_mesh(str(mesh_path)).sample_points_uniformly(200000)
    cloud = o3d.io.read_point_cloud(str(cloud_path))
    out = {}
    for name, a, b in (("mesh_to_sensor", mesh_pts, sensor), ("sensor_to_mesh", sensor, mesh_pts),
                       ("cloud_to_sensor", cloud, sensor)):
        d = np.asarray(a.compute_point_cloud_distance(b))
        out[name] = {"mean": float(d.mean()), "median": float(np.median(d)), "p90": float(np.percentile(d, 90))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data/7scenes_redkitchen_jpg1000")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--updates", type=int, default=4)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--kill-at", type=int, default=170, help="SIGKILL after this many source frames")
    ap.add_argument("--out", type=Path, default=Path("runs/resume_experiment"))
    ap.add_argument("--voxel-size", type=float, default=0.02)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--resume", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--run-dir", help=argparse.SUPPRESS)
    ap.add_argument("--ck", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "checkpoint.pt").unlink(missing_ok=True)
    wall, lines, last_ck = three_runs(args)

    import torch

    a = json.loads((args.out / "reference" / "result.json").read_text())
    b = json.loads((args.out / "resumed" / "result.json").read_text())
    pa, pb = torch.load(args.out / "reference" / "params.pt"), torch.load(args.out / "resumed" / "params.pt")
    identical = pa.keys() == pb.keys() and all(pa[k].shape == pb[k].shape and torch.equal(pa[k], pb[k]) for k in pa)
    exp, wall["export"] = export_and_pictures(args)
    geometry = geometry_vs_sensor(args.data, args.frames, args.out / "mesh.ply", args.out / "cloud.ply")
    results = {
        "data": args.data, "frames": args.frames, "updates_per_frame": args.updates,
        "checkpoint_every_source_frames": args.every, "killed_after_source_frames": args.kill_at,
        "last_checkpoint_before_kill": last_ck, "recomputed_source_frames": args.kill_at - last_ck,
        "reference": a, "resumed": b, "params_identical": identical,
        "psnr_difference_db": b["heldout_psnr"] - a["heldout_psnr"],
        "wall_s": wall, "export": exp, "geometry_vs_heldout_sensor_depth_m": geometry,
    }
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    md = summary_lines(args, results, sum(line.startswith("checkpoint") for line in lines))
    (args.out / "summary.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def three_runs(args) -> tuple[dict, list[str], int]:
    """The reference run, the run SIGKILLed after ``--kill-at`` source frames and its resumption: wall times (s),
    the killed run's output lines and the source frame of its last checkpoint."""
    t0 = time.perf_counter()
    ref = _spawn(args, args.out / "reference", "--every", "0")
    _finish(ref, args.out / "reference.log")
    ref_s = time.perf_counter() - t0
    print(f"reference run: {ref_s:.0f} s", flush=True)

    t0 = time.perf_counter()
    killed = _spawn(args, args.out / "killed", "--every", str(args.every))
    lines = []
    for line in killed.stdout:
        lines.append(line)
        if line.startswith("frame") and int(line.split()[3]) >= args.kill_at:
            killed.send_signal(signal.SIGKILL)
            break
    killed.wait()
    killed_s = time.perf_counter() - t0
    (args.out / "killed.log").write_text("".join(lines) + f"[SIGKILL, returncode {killed.returncode}]\n")
    last_ck = max((int(line.split()[2]) for line in lines if line.startswith("checkpoint")), default=0)
    print(f"killed after source frame {args.kill_at} ({killed_s:.0f} s), last checkpoint at {last_ck}", flush=True)

    t0 = time.perf_counter()
    res = _spawn(args, args.out / "resumed", "--every", str(args.every), "--resume")
    _finish(res, args.out / "resumed.log")
    resumed_s = time.perf_counter() - t0
    return {"reference": ref_s, "killed": killed_s, "resume": resumed_s}, lines, last_ck


def export_and_pictures(args) -> tuple[dict, float]:
    """The resumed map exported to mesh.ply and cloud.ply, and two PNGs of the mesh (a step behind the first camera,
    an overview from behind and above the cameras); (the export's summary, its wall time in s)."""
    import open3d as o3d

    from eligsir_o3d.core.camera import Camera
    from eligsir_o3d.datasets.base import read_tum_trajectory
    from eligsir_o3d.core.camera import look_at
    from eligsir_o3d.export import export_from_ply

    t0 = time.perf_counter()
    exp = export_from_ply(args.out / "resumed" / "map.ply", mesh_path=args.out / "mesh.ply",
                          cloud_path=args.out / "cloud.ply", voxel_size=args.voxel_size, depth_max=4.0)
    export_s = time.perf_counter() - t0
    _, poses = read_tum_trajectory(args.out / "resumed" / "trajectory.txt")
    cam = Camera(**exp["camera"])
    centres = np.stack([T[:3, 3] for T in poses])
    bbox = o3d.io.read_triangle_mesh(str(args.out / "mesh.ply")).get_axis_aligned_bounding_box()
    centre = bbox.get_center()
    back = poses[0].copy()
    back[:3, 3] -= 0.6 * back[:3, 2]  # a step behind the first camera
    render_mesh_png(args.out / "mesh.ply", args.out / "mesh_first_view.png", back, cam)
    up = -np.asarray(poses[0][:3, 1])  # OpenCV y points down in the image
    eye = centre + 1.5 * (centres.mean(0) - centre) + 1.0 * up  # behind and above the cameras
    render_mesh_png(args.out / "mesh.ply", args.out / "mesh_overview.png", look_at(eye, centre, up=up), cam)
    return exp, export_s


def summary_lines(args, results: dict, written_before_kill: int) -> list[str]:
    """summary.md, line by line, from results.json's dict."""
    a, b, exp, geometry = results["reference"], results["resumed"], results["export"], \
        results["geometry_vs_heldout_sensor_depth_m"]
    last_ck, wall = results["last_checkpoint_before_kill"], results["wall_s"]
    ck = b["checkpoints"]  # the resumed process's own saves (those of the killed one are in killed.log)
    return [f"# Resume after SIGKILL: {Path(args.data).name}, first {args.frames} frames",
            "",
            f"- killed (SIGKILL) after {args.kill_at} source frames; last checkpoint at {last_ck}; "
            f"{args.kill_at - last_ck} frames recomputed on resume",
            f"- held-out PSNR: reference {a['heldout_psnr']:.3f} dB, resumed {b['heldout_psnr']:.3f} dB "
            f"(difference {results['psnr_difference_db']:+.3f} dB); depth RMSE {a['heldout_depth_rmse_m']:.3f} / "
            f"{b['heldout_depth_rmse_m']:.3f} m",
            f"- final Gaussian parameters bit-identical: {results['params_identical']}; frames released "
            f"{a['frames_released']} / {b['frames_released']}; updates {a['updates']} / {b['updates']}; Gaussians "
            f"{a['gaussians']} / {b['gaussians']}",
            f"- checkpoints (views as sequence references): {written_before_kill} written before the kill, "
            f"{len(ck)} after; {np.mean([c['seconds'] for c in ck]):.3f} s and "
            f"{np.mean([c['bytes'] for c in ck]) / 1e6:.2f} MB each" if ck else "- no checkpoints",
            f"- wall time: reference {wall['reference']:.0f} s, killed run {wall['killed']:.0f} s, resumed run "
            f"{wall['resume']:.0f} s",
            f"- export: {exp['views']} views ({exp['view_source']}), mesh {exp['vertices']} vertices / "
            f"{exp['triangles']} triangles, cloud {exp['points']} points, {wall['export']:.1f} s",
            "- exported geometry vs held-out sensor depth (median / p90, cm): mesh->sensor "
            f"{100 * geometry['mesh_to_sensor']['median']:.1f} / {100 * geometry['mesh_to_sensor']['p90']:.1f}, "
            f"sensor->mesh {100 * geometry['sensor_to_mesh']['median']:.1f} / "
            f"{100 * geometry['sensor_to_mesh']['p90']:.1f}, cloud->sensor "
            f"{100 * geometry['cloud_to_sensor']['median']:.1f} / {100 * geometry['cloud_to_sensor']['p90']:.1f}",
            f"- peak RSS: reference {a['peak_rss_mb']:.0f} MB, resumed {b['peak_rss_mb']:.0f} MB"]


if __name__ == "__main__":
    main()
