"""Where does more compute buy most? A run's map, continued for the same CPU seconds in several ways, scored beside
the classical peer.

Every arm starts from what a results folder of ``eligsir map`` holds (``map.ply``, the views the run admitted in
``views_trace.csv``, its config, split and poses) and gets the same CPU seconds of one thread (process time, so
the figures hold on a shared machine):

- ``scale S`` (``--scales``): more updates of the run's own map, all supervised at scale S (0.25, 0.5, 1);
- ``fused`` (``--fused-voxel V``): the map replaced by one built from Open3D's TSDF of *all* the run's source
  frames (the surface points of a ``VoxelBlockGrid`` at V metres, coloured by the fusion, isotropic at half a
  voxel, opacity 0.95: seeds from depth averaged over every frame, sharp geometry from the start), then updates at
  1/4 scale; the fusion's own time is reported, not charged. It asks whether seeds from fused depth beat the
  run's own growth per second.

Each arm is scored at the held-out given poses as ``tsdf_baseline.py`` scores a run: PSNR on the pixels the TSDF
peer (1 cm) covers and on the whole image. The first row is the run's map as it is.

    python benchmarks/quality/compute_returns.py RUN --seconds 8 --scales 0.25 0.5 1 --fused-voxel 0.02
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np


def _peer():
    """tsdf_baseline.py beside this file, however this one runs (``python -m``, by path, or loaded by a test)."""
    spec = importlib.util.spec_from_file_location("tsdf_baseline", Path(__file__).with_name("tsdf_baseline.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


tb = _peer()


def admitted_views(folder: Path) -> list[int]:
    """Frame indices the run admitted as views (``admit`` events of its views_trace.csv), in admission order."""
    path = Path(folder) / "views_trace.csv"
    if not path.is_file():
        raise ValueError(f"{folder}: no views_trace.csv (the views the run admitted); map it again with this release")
    with path.open(newline="") as fh:
        views = [int(row["view"]) for row in csv.DictReader(fh) if row.get("event") == "admit"]
    if not views:
        raise ValueError(f"{path}: no 'admit' event: the run admitted no view to continue from")
    return views


def fused_points(seq, poses: dict, depth_max: float, voxel: float):
    """(points [M, 3], colours [M, 3]) of the TSDF surface fused from every frame of ``poses``, and seconds spent."""
    import torch

    t0 = time.perf_counter()
    vbg, _ = tb.fuse(seq, poses, depth_max, voxel)
    pc = vbg.extract_point_cloud(weight_threshold=tb.WEIGHT_THRESHOLD)
    pts = torch.from_numpy(pc.point.positions.numpy()).float()
    cols = torch.from_numpy(pc.point.colors.numpy()).float().clamp(0, 1)
    return pts, cols, time.perf_counter() - t0


class Scorer:
    """Held-out given poses of a run, the TSDF peer's coverage at each, and the renderer that draws a map there."""

    def __init__(self, seq, cfg, held: list[int], tsdf):
        import torch

        from eligsir_o3d.render import get_renderer

        self.seq, self.cfg = seq, cfg
        self.renderer = get_renderer(cfg.renderer, "cpu")
        self.background = torch.tensor(cfg.background, dtype=torch.float32)
        self.views = []
        for i in held:
            ref = seq.frame(i, depth_max=cfg.depth_max)
            _, depth = tsdf.render(seq.camera, ref.T_world_cam)
            self.views.append((ref.T_world_cam, ref.color.numpy(), depth > 0))

    def __call__(self, gmap) -> dict:
        import torch

        from eligsir_o3d.render import render_map

        covered, whole = [], []
        for T, gt, mask in self.views:
            with torch.no_grad():
                g = render_map(self.renderer, gmap, self.seq.camera, T, self.background).color.clamp(0, 1).numpy()
            covered.append(tb._psnr(g, gt, mask))
            whole.append(tb._psnr(g, gt))
        return {"covered": float(np.mean(covered)), "whole": float(np.mean(whole))}


def reconstructor_over(seq, cfg, poses: dict, views: list[int], start):
    """A Reconstructor whose views are the frames ``views`` at the run's poses and whose map is ``start`` (a PLY
    path or a GaussianMap): the run's state to continue from, without its stream."""
    from eligsir_o3d import Reconstructor

    rec = Reconstructor(seq.camera, "cpu", cfg)
    for i in views:
        retain = getattr(rec.views, "retain", None) or rec.views._admit  # an older checkout: the private name
        retain(seq.frame(i, depth_max=cfg.depth_max, T_world_cam=poses[i]))
    if isinstance(start, (str, Path)):
        rec.load_ply(start)
    else:
        rec.gmap = start
    return rec


def continue_map(seq, cfg, poses: dict, views: list[int], start, scale: float, seconds: float, chunk: int = 5):
    """:func:`reconstructor_over` the run's views and the map ``start``, updated at ``scale`` until ``seconds`` of
    process time are spent (whole chunks). Returns (map, updates, cpu seconds)."""
    rec = reconstructor_over(seq, cfg, poses, views, start)
    done, t0 = 0, time.process_time()
    while time.process_time() - t0 < seconds:
        done += rec.optimize(chunk, scale=scale)
    return rec.gmap, done, time.process_time() - t0


def evaluate(folder: str | Path, seconds: float, scales=(0.25, 0.5, 1.0), fused_voxel: float | None = None) -> dict:
    """Every arm of the module docstring on results folder ``folder``, ``seconds`` CPU seconds each."""
    import torch

    from eligsir_o3d.core.gaussians import GaussianMap
    from eligsir_o3d.io.ply import load_ply

    folder = Path(folder)
    seq, cfg, _, source, held, poses = tb.read_results(folder)
    if not held:
        raise ValueError(f"{folder}: the run held out no views: there is nothing to score the arms at")
    views = [i for i in admitted_views(folder) if i in poses]
    vbg, _ = tb.fuse(seq, poses, cfg.depth_max)
    score = Scorer(seq, cfg, held, tb.MeshRenderer(vbg.extract_triangle_mesh(weight_threshold=tb.WEIGHT_THRESHOLD)))
    run_map = load_ply(folder / "map.ply")
    rows = [{"arm": "the run's map", "updates": 0, "cpu_s": 0.0, "gaussians": len(run_map), **score(run_map)}]
    for s in scales:
        gmap, n, spent = continue_map(seq, cfg, poses, views, folder / "map.ply", float(s), seconds)
        rows.append({"arm": f"scale {float(s):g}", "updates": n, "cpu_s": spent, "gaussians": len(gmap),
                     **score(gmap)})
    out = {"results": str(folder), "seconds": seconds, "views": len(views), "heldout": len(held),
           "gaussians": len(run_map), "rows": rows}
    if fused_voxel:
        pts, cols, fuse_s = fused_points(seq, poses, cfg.depth_max, float(fused_voxel))
        gm = GaussianMap(cfg.sh_degree)
        gm.add(pts, cols, torch.full((pts.shape[0],), 0.5 * float(fused_voxel)), 0.95)
        seeded = score(gm)
        gmap, n, spent = continue_map(seq, cfg, poses, views, gm, 0.25, seconds)
        out["fused"] = {"voxel_m": float(fused_voxel), "frames": len(poses), "points": int(pts.shape[0]),
                        "fusion_s": fuse_s, "seeded": seeded}
        rows.append({"arm": f"fused {float(fused_voxel):g} m, scale 0.25", "updates": n, "cpu_s": spent,
                     "gaussians": len(gmap), **score(gmap)})
    return out


def format_table(r: dict) -> str:
    lines = [f"{r['results']}: {r['views']} views, {r['heldout']} held-out views, {r['seconds']:g} CPU s per arm "
             f"(one thread); held-out PSNR at the given poses, dB",
             f"  {'arm':<28} {'updates':>7} {'CPU s':>6} {'TSDF-covered':>12} {'whole':>6}"]
    for row in r["rows"]:
        lines.append(f"  {row['arm']:<28} {row['updates']:>7} {row['cpu_s']:>6.1f} {row['covered']:>12.2f} "
                     f"{row['whole']:>6.2f}")
    if "fused" in r:
        f = r["fused"]
        lines.append(f"  fused map before any update: {f['points']} Gaussians from {f['frames']} frames "
                     f"({f['fusion_s']:.1f} s to fuse), {f['seeded']['covered']:.2f} / {f['seeded']['whole']:.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="results folders of eligsir map")
    ap.add_argument("--seconds", type=float, default=8.0, help="CPU seconds of one thread per arm")
    ap.add_argument("--scales", type=float, nargs="*", default=[0.25, 0.5, 1.0])
    ap.add_argument("--fused-voxel", type=float, help="also the arm seeded from the TSDF at this voxel size (m)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    import numba
    import torch

    threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)  # CPU seconds of one thread: a measure of work on a shared machine
    numba.set_num_threads(1)
    try:
        for folder in args.results:
            try:
                r = evaluate(folder, args.seconds, args.scales, args.fused_voxel)
            except ValueError as e:
                print(f"compute_returns: {e}", file=sys.stderr)
                return 2
            print(json.dumps(r) if args.json else format_table(r), flush=True)
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
