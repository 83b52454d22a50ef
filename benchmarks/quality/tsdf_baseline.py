"""The classical peer: Open3D's own TSDF fusion of the same frames a run mapped, beside the run's Gaussian map.

Given a results folder of ``eligsir map`` (run.json and config.json name the sequence, the frame range, the held-out
split and the registration; trajectory.txt holds the poses the run mapped with), this

1. fuses the run's source (training) frames, at the same registered depth and colour and the same poses, into an
   Open3D ``t.geometry.VoxelBlockGrid`` TSDF (1 cm voxels, colour; ``integrate`` per frame);
2. renders the TSDF at every held-out view's given pose: the zero level set is extracted once with Open3D's
   marching cubes (``extract_triangle_mesh``) and ray-cast with ``RaycastingScene`` (ray through each pixel centre,
   colour interpolated from the mesh's vertex colours). ``VoxelBlockGrid.ray_cast`` is not used: in Open3D 0.20 its
   second call hangs whenever its range-map fragment buffer must grow (isl-org/Open3D#6821; reproduced here on the
   synthetic room), and it returns surfaces half a voxel off (NOTES-apis.md); the mesh needs neither workaround;
3. renders the run's map.ply at the same given poses with the package's renderer;
4. reports held-out PSNR (mean over views of per-view PSNR on [0, 1] colour): the TSDF on the whole image
   (unobserved pixels are black, the background a user sees) and on the pixels its surface covers, and the Gaussian
   map on those same covered pixels and on the whole image;
5. says where each render's error lies on the covered pixels (:func:`diagnose`): on the reference's detail (edges,
   texture) or flat pixels, in broad colour (after a common blur), and how far a whole-pixel shift of the render
   improves it (a held-out pose that disagrees with its image costs a sharp render more than a soft one), and
   names the held-out views where both renders match best shifted alike (:func:`pose_suspects`: the given pose,
   not either map, is off there).

Poses: the TSDF uses the run's source poses as mapped (trajectory.txt) and the held-out views' given poses, the
strict rule ("given"); with pose refinement the Gaussian map is also scored at the paper's rule ("aligned": the
given held-out poses after one rigid alignment of the mapped poses to the refined ones, trajectory_refined.txt).

    python benchmarks/quality/tsdf_baseline.py runs/kitchen                      # table
    python benchmarks/quality/tsdf_baseline.py runs/kitchen --json --pictures /tmp/peer/pics --views 3 17
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch (NOTES-apis.md: spin-waiting starves the main thread)

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

VOXEL_SIZE = 0.01  # metres: 1 cm voxels
TRUNC_VOXELS = 8.0  # truncation in voxels (Open3D's default trunc_voxel_multiplier)
WEIGHT_THRESHOLD = 1.0  # marching cubes keeps voxels whose weight exceeds this: seen by more than one frame


def read_results(folder: str | Path):
    """(sequence, Config, RunOptions, source indices, held-out indices, source poses {index: T_world_cam [4, 4]})
    of a results folder; the source poses are those of its trajectory.txt (matched to frames by timestamp)."""
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.run.pipeline import heldout_indices, read_run
    from eligsir_o3d.pose.trajectory import nearest_index, read_tum_trajectory

    folder = Path(folder)
    path, cfg, opts = read_run(folder)
    seq = open_sequence(path, **(opts.sequence_options or {}))
    n = len(seq) if opts.max_frames is None else min(len(seq), int(opts.max_frames))
    held = heldout_indices(n, opts.holdout_every, opts.holdout_list)
    source = [i for i in range(n) if i not in set(held)]
    traj = folder / "trajectory.txt"
    if not traj.is_file():
        raise ValueError(f"{folder}: no trajectory.txt (the poses the run mapped with)")
    stamps, poses = read_tum_trajectory(traj)
    mapped = {}
    for i in source:
        k, dt = nearest_index(np.asarray(stamps), float(seq.timestamps[i]))
        if abs(dt) <= 1e-4:
            mapped[i] = poses[k]
    if not mapped:
        raise ValueError(f"{traj}: no pose matches a source frame's timestamp")
    return seq, cfg, opts, source, held, mapped


def fuse(seq, poses: dict, depth_max: float, voxel_size: float = VOXEL_SIZE, trunc_voxels: float = TRUNC_VOXELS):
    """A colour TSDF (VoxelBlockGrid) of the frames ``poses`` names ({index: T_world_cam}); returns (vbg, s/frame)."""
    import open3d as o3d
    import open3d.core as o3c

    from eligsir_o3d.core.camera import extrinsic_from_pose

    dev = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight", "color"), (o3c.float32, o3c.float32, o3c.float32),
                                        (1, 1, 3), voxel_size, 16, 10000, dev)  # the hash map grows as needed
    K = o3c.Tensor(seq.camera.K, o3c.float64)
    spent = 0.0
    for i, T in sorted(poses.items()):
        f = seq.frame(i, depth_max=depth_max, T_world_cam=T)
        depth = o3d.t.geometry.Image(o3c.Tensor(f.depth.numpy()))
        color = o3d.t.geometry.Image(o3c.Tensor(f.color.numpy()))
        ext = o3c.Tensor(extrinsic_from_pose(T), o3c.float64)  # Open3D's extrinsic: world-to-camera
        t0 = time.perf_counter()
        blocks = vbg.compute_unique_block_coordinates(depth, K, ext, 1.0, depth_max, trunc_voxels)
        vbg.integrate(blocks, depth, color, K, ext, 1.0, depth_max, trunc_voxels)
        spent += time.perf_counter() - t0
    return vbg, spent / max(1, len(poses))


class MeshRenderer:
    """Ray-casts a colour triangle mesh (the TSDF's zero level set) through pixel centres at integer coordinates."""

    def __init__(self, mesh):
        import open3d as o3d
        import open3d.core as o3c

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh.vertex.positions.to(o3c.float32), mesh.triangle.indices.to(o3c.uint32))
        self.tris = mesh.triangle.indices.numpy().astype(np.int64)  # [T, 3]
        self.colors = mesh.vertex.colors.numpy().astype(np.float32)  # [V, 3] in [0, 1]

    def render(self, camera, T_world_cam) -> tuple[np.ndarray, np.ndarray]:
        """(colour [H, W, 3] in [0, 1], black where nothing is hit; z-depth [H, W] metres, 0 where nothing is hit)."""
        import open3d.core as o3c

        from eligsir_o3d.core.camera import extrinsic_from_pose

        K = np.asarray(camera.K, dtype=np.float64).copy()
        K[0, 2] += 0.5  # create_rays_pinhole shoots through (u + 0.5, v + 0.5): centres at integers need cx + 0.5
        K[1, 2] += 0.5
        rays = self.scene.create_rays_pinhole(o3c.Tensor(K), o3c.Tensor(extrinsic_from_pose(T_world_cam)),
                                              camera.width, camera.height)
        ans = self.scene.cast_rays(rays)
        t = ans["t_hit"].numpy()  # ray directions have z = 1 in the camera: t is z-depth
        hit = np.isfinite(t)
        prim = ans["primitive_ids"].numpy()[hit].astype(np.int64)
        uv = ans["primitive_uvs"].numpy()[hit]
        tri = self.tris[prim]
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)[..., None]  # barycentric weights
        color = np.zeros((camera.height, camera.width, 3), np.float32)
        color[hit] = np.clip((self.colors[tri] * w).sum(1), 0.0, 1.0)
        depth = np.where(hit, t, 0.0).astype(np.float32)
        return color, depth


def _psnr(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    from eligsir_o3d.eval import psnr
    import torch

    return psnr(torch.from_numpy(pred), torch.from_numpy(ref), None if mask is None else torch.from_numpy(mask))


def aligned_transform(folder: Path) -> np.ndarray | None:
    """T_refined_given of a pose-refined run (one rigid motion from the mapped poses to the refined ones, the
    paper's training-pose alignment), None when the run wrote no trajectory_refined.txt."""
    from eligsir_o3d.pose.accuracy import pose_alignment
    from eligsir_o3d.pose.trajectory import read_tum_trajectory

    refined = folder / "trajectory_refined.txt"
    if not refined.is_file():
        return None
    _, given = read_tum_trajectory(folder / "trajectory.txt")
    _, moved = read_tum_trajectory(refined)
    return pose_alignment(given, moved)


def evaluate(folder: str | Path, voxel_size: float = VOXEL_SIZE, weight_threshold: float = WEIGHT_THRESHOLD,
             pictures: str | Path | None = None, picture_views: tuple[int, ...] = ()) -> dict:
    """The TSDF peer and the Gaussian map of results folder ``folder`` at its held-out views (see the module
    docstring); ``pictures``: a folder for Gaussian | TSDF | reference PNGs of the held-out views at the positions
    ``picture_views`` in the split (all when empty)."""
    import torch

    from eligsir_o3d.io.ply import load_ply
    from eligsir_o3d.render import get_renderer, render_map

    folder = Path(folder)
    seq, cfg, opts, source, held, poses = read_results(folder)
    if not held:
        raise ValueError(f"{folder}: the run held out no views ({len(source)} source frames, holdout every "
                         f"{opts.holdout_every}): there is nothing to score either map at")
    t0 = time.perf_counter()
    vbg, per_frame_s = fuse(seq, poses, cfg.depth_max, voxel_size)
    tsdf = MeshRenderer(vbg.extract_triangle_mesh(weight_threshold=weight_threshold))
    fuse_s = time.perf_counter() - t0
    gmap = load_ply(folder / "map.ply")
    renderer = get_renderer(cfg.renderer, "cpu")
    background = torch.tensor(cfg.background, dtype=torch.float32)
    T_align = aligned_transform(folder)
    rows = []
    for k, i in enumerate(held):
        ref = seq.frame(i, depth_max=cfg.depth_max)
        gt = ref.color.numpy()
        t_color, t_depth = tsdf.render(seq.camera, ref.T_world_cam)
        covered = t_depth > 0
        with torch.no_grad():
            out = render_map(renderer, gmap, seq.camera, ref.T_world_cam, background)  # as eligsir map scores it
            g, g_alpha = out.color.clamp(0, 1).numpy(), out.alpha.numpy()
            ga = None
            if T_align is not None:
                ga = render_map(renderer, gmap, seq.camera, T_align @ ref.T_world_cam,
                                background).color.clamp(0, 1).numpy()
        row = {"index": i, "coverage": float(covered.mean()), "tsdf_whole": _psnr(t_color, gt),
               "tsdf_covered": _psnr(t_color, gt, covered), "gaussian_whole": _psnr(g, gt),
               "gaussian_covered": _psnr(g, gt, covered)}
        if ga is not None:
            row.update(gaussian_aligned_whole=_psnr(ga, gt), gaussian_aligned_covered=_psnr(ga, gt, covered))
        row.update(diagnose(g, t_color, gt, covered, g_alpha > 0.5))
        rows.append(row)
        if pictures is not None and (not picture_views or k in picture_views):
            _picture(Path(pictures) / f"heldout_{i:05d}.png", g, t_color, gt)
    keys = [k for k in rows[0] if k != "index" and not k.endswith(("_dx", "_dy"))]
    summary = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    # where along the recording the map leads or trails the peer: held-out views in stream order, in thirds
    summary["margin_by_third"] = [float(np.mean([r["gaussian_covered"] - r["tsdf_covered"] for r in part]))
                                  for part in np.array_split(np.array(rows, dtype=object), 3) if len(part)]
    summary["pose_suspects"] = pose_suspects(rows)
    return {"results": str(folder), "sequence": str(seq.path), "frames_source": len(poses), "views": len(rows),
            "voxel_size_m": voxel_size, "weight_threshold": weight_threshold, "tsdf_blocks": int(vbg.hashmap().size()),
            "tsdf_integrate_ms_per_frame": 1e3 * per_frame_s, "tsdf_build_s": fuse_s,
            "gaussians": len(gmap), **summary, "per_view": rows}


SUSPECT_SHIFT_PX = 4.0  # both renders match their reference best this far off: the view's given pose is off
SUSPECT_AGREE_PX = 2.0  # ... and in the same direction (within this), so neither map is what is off


def pose_suspects(rows: list[dict]) -> list[dict]:
    """The held-out views whose given pose disagrees with their image: the Gaussian render and the TSDF render,
    two maps built differently from the same source frames, both match the reference best when shifted at least
    :data:`SUSPECT_SHIFT_PX` pixels, by shifts that agree within :data:`SUSPECT_AGREE_PX`. Such a view scores both
    maps low whatever they hold (on the SUN3D study room, held-out frame 28 at 11-12 px up: 15.4 / 15.7 dB where the
    shifted renders score 23.7 / 23.7), so a few of them move a short split's mean by a decibel. Each: the view's
    frame index, the shift (px, right and down positive) and the PSNR on the covered pixels there and as given."""
    out = []
    for r in rows:
        g, t = (r["gaussian_shift_dx"], r["gaussian_shift_dy"]), (r["tsdf_shift_dx"], r["tsdf_shift_dy"])
        if min(np.hypot(*g), np.hypot(*t)) >= SUSPECT_SHIFT_PX and \
                np.hypot(g[0] - t[0], g[1] - t[1]) <= SUSPECT_AGREE_PX:
            out.append({"index": r["index"], "shift_px": [int(g[0]), int(g[1])],
                        "gaussian": [r["gaussian_covered"], r["gaussian_shifted"]],
                        "tsdf": [r["tsdf_covered"], r["tsdf_shifted"]]})
    return out


def diagnose(g: np.ndarray, t: np.ndarray, gt: np.ndarray, covered: np.ndarray, g_valid: np.ndarray) -> dict:
    """Where each render's error lies on the covered pixels (:mod:`eligsir_o3d.eval.detail`): PSNR on the
    reference's detail (its 20 % of pixels with the largest gradient) and on the rest, PSNR after a common blur
    (broad colour), and the whole-pixel shift that matches the reference best, with the PSNR there. A render's
    holes move with it when it is shifted: the TSDF's uncovered pixels, the Gaussian map's pixels of opacity
    below 0.5 (``g_valid`` marks the others)."""
    from eligsir_o3d.eval.detail import best_shift, detail_split

    row = {}
    for name, img, valid in (("gaussian", g, g_valid), ("tsdf", t, covered)):
        d, s = detail_split(img, gt, covered), best_shift(img, gt, covered, valid=valid)
        row.update({f"{name}_detail": d["detail"], f"{name}_flat": d["flat"], f"{name}_lowpass": d["lowpass"],
                    f"{name}_shift_px": float(np.hypot(s["dx"], s["dy"])), f"{name}_shifted": s["psnr"],
                    f"{name}_shift_dx": s["dx"], f"{name}_shift_dy": s["dy"]})
    return row


def _picture(path: Path, *images: np.ndarray) -> None:
    """One PNG of the images side by side (left to right), each [H, W, 3] in [0, 1]."""
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    gap = np.ones((images[0].shape[0], 4, 3), np.float32)
    row = np.concatenate([x for im in images for x in (im, gap)][:-1], axis=1)
    iio.imwrite(path, (np.clip(row, 0, 1) * 255 + 0.5).astype(np.uint8))


def format_table(r: dict) -> str:
    lines = [f"{r['results']}: {r['views']} held-out views, {r['frames_source']} source frames, "
             f"TSDF {r['voxel_size_m'] * 100:g} cm ({r['tsdf_integrate_ms_per_frame']:.0f} ms/frame integrate), "
             f"map {r['gaussians']} Gaussians",
             f"  TSDF      whole image {r['tsdf_whole']:6.2f} dB   on its covered pixels ({100 * r['coverage']:.1f} %) "
             f"{r['tsdf_covered']:6.2f} dB",
             f"  Gaussian  whole image {r['gaussian_whole']:6.2f} dB   on the TSDF's covered pixels "
             f"{r['gaussian_covered']:6.2f} dB   (given poses)"]
    if "gaussian_aligned_whole" in r:
        lines.append(f"  Gaussian  whole image {r['gaussian_aligned_whole']:6.2f} dB   on the TSDF's covered pixels "
                     f"{r['gaussian_aligned_covered']:6.2f} dB   (aligned: the paper's rule)")
    lines.append("  where the error lies, covered pixels (dB; Gaussian / TSDF): detail (20 % by gradient) "
                 f"{r['gaussian_detail']:.2f} / {r['tsdf_detail']:.2f}, flat {r['gaussian_flat']:.2f} / "
                 f"{r['tsdf_flat']:.2f}, broad colour {r['gaussian_lowpass']:.2f} / {r['tsdf_lowpass']:.2f}; "
                 f"best shift {r['gaussian_shift_px']:.1f} / {r['tsdf_shift_px']:.1f} px, there "
                 f"{r['gaussian_shifted']:.2f} / {r['tsdf_shifted']:.2f}")
    if r.get("margin_by_third"):
        lines.append("  Gaussian - TSDF on the covered pixels, held-out views in stream order by thirds "
                     "(start / middle / end): " + " / ".join(f"{m:+.2f}" for m in r["margin_by_third"]) + " dB")
    sus = r.get("pose_suspects") or []
    if sus:
        lines.append(f"  held-out views whose given pose disagrees with their image ({len(sus)} of {r['views']}; both "
                     "renders match best shifted alike): " + ", ".join(
                         f"frame {v['index']} by ({v['shift_px'][0]:+d}, {v['shift_px'][1]:+d}) px, Gaussian "
                         f"{v['gaussian'][0]:.2f} -> {v['gaussian'][1]:.2f}, TSDF {v['tsdf'][0]:.2f} -> "
                         f"{v['tsdf'][1]:.2f} dB" for v in sus))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="results folders of eligsir map")
    ap.add_argument("--voxel-size", type=float, default=VOXEL_SIZE)
    ap.add_argument("--weight-threshold", type=float, default=WEIGHT_THRESHOLD)
    ap.add_argument("--pictures", help="folder for Gaussian | TSDF | reference PNGs")
    ap.add_argument("--views", type=int, nargs="*", default=[], help="positions in the held-out split to picture")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    for folder in a.results:
        try:
            r = evaluate(folder, a.voxel_size, a.weight_threshold, a.pictures, tuple(a.views))
        except (ValueError, OSError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(json.dumps({k: v for k, v in r.items() if k != "per_view"}, indent=1) if a.json else format_table(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
