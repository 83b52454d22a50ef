"""Fit the budget clock's cost model (``clock.cost``) to this machine on a long real recording (the offline,
thorough counterpart of the few-second ``Reconstructor.calibrate()`` that ``eligsir map`` runs and caches).

The deterministic cost clock (the default ``clock.mode=cost``) replays a recording against
*modelled* time: each update costs ``update_s + gaussian_s*N + P*(pixel_s + pixel_gaussian_s*N)`` seconds and each
integrated frame ``frame_s + gaussian_s*N``. A model slower than the machine gives the mapper fewer updates than it
could afford in real time; a faster one lets it fall behind. This script measures the real mapper on a real recording
and fits the constants:

- it maps the first ``--frames`` frames of ``../shared/data/7scenes_redkitchen_jpg1000`` (every 8th held out, as the
  pipeline does) with the default policies and the chosen renderer;
- after each integrated frame (timed: admission, growth) it runs ``--updates`` updates at each fidelity scale
  in turn (each timed alone: select, render, loss, backward, Adam, policies' feedback), so every scale is sampled on
  every map size the run passes through;
- ``CostModel.fit`` (non-negative least squares on relative error: every sample weighs the same whatever its
  size) gives the constants; it prints them, the median and 90th-percentile error of the fit, and how the current defaults compare.

    python benchmarks/budget/cost_model.py                     # table + fitted constants
    python benchmarks/budget/cost_model.py --json runs/cost.json
    eligsir map ... --cost-model runs/cost.json         # use them (or --config: a file with only {"clock": {"cost": ...}})

Time measurements are wall clock: run it on an otherwise idle machine (the 1-minute load average is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from eligsir_o3d import Config, Reconstructor  # noqa: E402
from eligsir_o3d.budget import CostModel  # noqa: E402
from eligsir_o3d.budget.calibrate import time_updates  # noqa: E402
from eligsir_o3d.datasets import open_sequence  # noqa: E402

KITCHEN = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"
UPDATE_TERMS = ("update_s", "gaussian_s", "pixel_s", "pixel_gaussian_s")


def collect(path: Path, frames: int, updates: int, scales: list[float], renderer: str, warmup: int):
    seq = open_sequence(path)
    cfg = Config(renderer=renderer)
    rec = Reconstructor(seq.camera, device="cpu", config=cfg)
    source = [i for i in range(min(frames, len(seq))) if i % 8 != 4]
    # the same timing loop as the calibration eligsir map runs (budget/calibrate.py), over a whole recording
    update_rows, frame_rows = time_updates(rec, (seq.frame(i, depth_max=cfg.depth_max) for i in source), scales,
                                           updates, warmup)
    return frame_rows, update_rows


def errors(model: CostModel, update_rows: np.ndarray) -> np.ndarray:
    pred = np.array([model.update(int(p), int(g)) for p, g, _ in update_rows])
    return pred / update_rows[:, 2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=KITCHEN)
    ap.add_argument("--frames", type=int, default=160, help="frames of the recording to map (default 160)")
    ap.add_argument("--updates", type=int, default=2, help="timed updates per scale after each frame")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.125, 0.25, 0.5, 1.0])
    ap.add_argument("--renderer", default="cpu")
    ap.add_argument("--warmup", type=int, default=3, help="frames whose timings are dropped (compilation, caches)")
    ap.add_argument("--json", type=Path, help="write {'clock': {'cost': ...}} here, a config file for --config")
    args = ap.parse_args(argv)

    import torch

    print(f"# renderer={args.renderer} torch_threads={torch.get_num_threads()} cpu_count={os.cpu_count()} "
          f"loadavg_1min={os.getloadavg()[0]:.2f} frames={args.frames} scales={args.scales}")
    frame_rows, update_rows = collect(args.data, args.frames, args.updates, args.scales, args.renderer, args.warmup)
    model = CostModel.fit(update_rows, frame_rows)
    print(f"{len(update_rows)} update samples ({update_rows[:, 1].min():.0f}-{update_rows[:, 1].max():.0f} Gaussians), "
          f"{len(frame_rows)} frame samples")
    print(f"{'scale':>6} {'pixels':>7} {'n':>4} {'measured_ms':>12} {'fitted_ms':>10} {'defaults_ms':>12}")
    default = CostModel()
    for px in sorted(set(update_rows[:, 0].astype(int))):
        rows = update_rows[update_rows[:, 0] == px]
        g = int(np.median(rows[:, 1]))
        print(f"{np.sqrt(px / 307200):6.3f} {px:7d} {len(rows):4d} {1e3 * np.median(rows[:, 2]):12.1f} "
              f"{1e3 * model.update(px, g):10.1f} {1e3 * default.update(px, g):12.1f}")
    for name, m in (("fitted", model), ("defaults", default)):
        r = errors(m, update_rows)
        total = sum(m.update(int(p), int(g)) for p, g, _ in update_rows) / update_rows[:, 2].sum()
        print(f"{name:>8}: predicted/measured per update: median {np.median(r):.2f}, "
              f"10-90% {np.percentile(r, 10):.2f}-{np.percentile(r, 90):.2f}; sum over all updates {total:.2f}")
    tf = frame_rows[:, 1]
    print(f"frame (admission + growth): measured mean {1e3 * np.mean(tf):.1f} ms, fitted "
          f"{1e3 * np.mean([model.frame(int(g)) for g in frame_rows[:, 0]]):.1f} ms, defaults "
          f"{1e3 * np.mean([default.frame(int(g)) for g in frame_rows[:, 0]]):.1f} ms")
    consts = {k: float(f"{getattr(model, k):.3g}") for k in UPDATE_TERMS + ("frame_s",)}
    print("fitted:", json.dumps(consts))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"clock": {"cost": consts}}, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
