"""Does the map fit the views it was trained on? A run's training views beside its held-out views, and how fast
its map fits one view, a few, or all of them when it is given more updates.

PSNR on the whole image at the run's own poses (the given poses of the held-out views, as ``eligsir map`` scores
them), at full size and at the scale most of the run's updates supervised (render and reference both area-averaged
to it, as the supervision pyramid is), dB:

- the run's map on its admitted views (the views its updates supervised), on its other source frames (every
  ``--stride``-th; seen by the stream, never supervised) and on its held-out views;
- ``--views K ...``: the run's map continued for ``--updates`` more updates over K of its admitted views, evenly
  spaced (0: all of them), at that scale, scored on those K views before and after, and on the held-out views after.

Reading it: a map that scores its training views far above its held-out ones overfits them (too few views, or pose
error between them); one that scores both alike under-fits. If it then fits one view in a few dozen updates but
all its views together slowly, the views compete for the same Gaussians: what the map lacks is updates (or
Gaussians) per view, not a step size. Stop 50 in docs/evaluation.md measured this on the kitchen and study room.

    python benchmarks/quality/fit_gap.py RUN --updates 400 --views 1 4 0
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np


def _sibling(name: str):
    """A script beside this file, however this one runs (``python -m``, by path, or loaded by a test)."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


cr = _sibling("compute_returns")
tb = cr.tb


def update_scale(folder: Path) -> float:
    """The supervision scale most of the run's updates ran at (``metrics.json``; 0.25 when it does not say)."""
    path = Path(folder) / "metrics.json"
    by_scale = {}
    if path.is_file():
        by_scale = json.loads(path.read_text()).get("policies", {}).get("fidelity", {}).get("updates_by_scale", {})
    return float(max(by_scale, key=by_scale.get)) if by_scale else 0.25


def area_average(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, C] averaged over factor x factor blocks (the image cropped to whole blocks)."""
    if factor <= 1:
        return image
    h, w = image.shape[0] // factor * factor, image.shape[1] // factor * factor
    blocks = image[:h, :w].reshape(h // factor, factor, w // factor, factor, -1)
    return blocks.mean((1, 3))


class Frames:
    """Frames of a run at fixed poses, each scored at full size and at the run's update scale."""

    def __init__(self, seq, cfg, indices, poses: dict | None, scale: float):
        import torch

        from eligsir_o3d.render import get_renderer

        self.seq, self.factor = seq, max(1, round(1.0 / scale))
        self.renderer = get_renderer(cfg.renderer, "cpu")
        self.background = torch.tensor(cfg.background, dtype=torch.float32)
        self.frames = []
        for i in indices:
            f = seq.frame(i, depth_max=cfg.depth_max)
            self.frames.append((poses[i] if poses is not None else f.T_world_cam, f.color.numpy()))

    def __len__(self) -> int:
        return len(self.frames)

    def __call__(self, gmap) -> dict:
        """{"full": mean PSNR at full size, "scaled": mean PSNR at the update scale} of ``gmap`` on these frames."""
        import torch

        from eligsir_o3d.render import render_map

        full, scaled = [], []
        for T, gt in self.frames:
            with torch.no_grad():
                g = render_map(self.renderer, gmap, self.seq.camera, T, self.background).color.clamp(0, 1).numpy()
            full.append(tb._psnr(g, gt))
            scaled.append(tb._psnr(area_average(g, self.factor), area_average(gt, self.factor)))
        return {"full": float(np.mean(full)), "scaled": float(np.mean(scaled))}


def evenly(items: list, k: int) -> list:
    """k of ``items`` spread evenly over the list (all of them when k is 0 or at least their number)."""
    if k <= 0 or k >= len(items):
        return list(items)
    if k == 1:
        return [items[len(items) // 2]]
    return [items[round(j * (len(items) - 1) / (k - 1))] for j in range(k)]


def evaluate(folder: str | Path, updates: int = 400, view_counts=(1, 4, 0), stride: int = 4) -> dict:
    """The rows of the module docstring for results folder ``folder``."""
    from eligsir_o3d.io.ply import load_ply

    folder = Path(folder)
    seq, cfg, _, source, held, poses = tb.read_results(folder)
    if not held:
        raise ValueError(f"{folder}: the run held out no views: there is nothing to compare its training views with")
    views = [i for i in cr.admitted_views(folder) if i in poses]
    scale = update_scale(folder)
    others = [i for i in source if i in poses and i not in set(views)][::max(1, stride)]
    heldout = Frames(seq, cfg, held, None, scale)  # the given poses, as eligsir map scores them
    run_map = load_ply(folder / "map.ply")
    rows = [{"frames": name, "n": len(fr), **fr(run_map)}
            for name, fr in (("admitted views", Frames(seq, cfg, views, poses, scale)),
                             ("other source frames", Frames(seq, cfg, others, poses, scale)),
                             ("held-out views", heldout)) if len(fr)]
    fits = []
    for k in view_counts:
        picked = evenly(views, int(k))
        own = Frames(seq, cfg, picked, poses, scale)
        rec = cr.reconstructor_over(seq, cfg, poses, picked, folder / "map.ply")
        before = own(rec.gmap)
        done = rec.optimize(int(updates), scale=scale)
        fits.append({"views": len(picked), "updates": done, "gaussians": len(rec.gmap), "before": before,
                     "after": own(rec.gmap), "heldout_after": heldout(rec.gmap)})
    return {"results": str(folder), "scale": scale, "gaussians": len(run_map), "views": len(views), "rows": rows,
            "fits": fits}


def format_table(r: dict) -> str:
    s = f"1/{round(1 / r['scale'])}"
    lines = [f"{r['results']}: {r['gaussians']} Gaussians, {r['views']} admitted views; PSNR on the whole image, "
             f"full size / area-averaged to the updates' scale {s}, dB",
             f"  {'frames':<22} {'n':>4} {'full':>6} {s:>6}"]
    for row in r["rows"]:
        lines.append(f"  {row['frames']:<22} {row['n']:>4} {row['full']:>6.2f} {row['scaled']:>6.2f}")
    if r["fits"]:
        lines.append(f"  the run's map continued over K of its views at {s}: those views at {s}, before -> after; "
                     "held-out after (full)")
        for f in r["fits"]:
            lines.append(f"  K = {f['views']:<3} {f['updates']:>5} updates  {f['before']['scaled']:6.2f} -> "
                         f"{f['after']['scaled']:6.2f}   held-out {f['heldout_after']['full']:6.2f}   "
                         f"{f['gaussians']} Gaussians")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", help="results folders of eligsir map")
    ap.add_argument("--updates", type=int, default=400, help="updates of each continuation")
    ap.add_argument("--views", type=int, nargs="*", default=[1, 4, 0],
                    help="continue over this many of the run's admitted views (0: all; none: no continuation)")
    ap.add_argument("--stride", type=int, default=4, help="score every this-th of the other source frames")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    for folder in args.results:
        try:
            r = evaluate(folder, args.updates, args.views, args.stride)
        except ValueError as e:
            print(f"fit_gap: {e}", file=sys.stderr)
            return 2
        print(json.dumps(r) if args.json else format_table(r), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
