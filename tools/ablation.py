#!/usr/bin/env python
"""The paper's Table III for one sequence: the full method and each ablation under the same held-out split and
the same budget, plus the Load-Adaptive Fidelity trace (the paper's Fig. 6).

    python tools/ablation.py ../shared/data/7scenes_redkitchen_jpg1000 --max-frames 300 --out runs/ablation

Variants: ``full`` (EliGSiR), ``fidelity`` (fixed native resolution), ``growth`` (dense per-frame depth insertion),
``scheduling`` (fixed-stride keyframes, uniform replay). Every variant is a separate ``run_mapping`` into
``OUT/<variant>`` (with ``--seeds``: ``OUT/<variant>-s<seed>``, and the table holds each variant's mean over the
seeds, with one row per run below it); the table is printed and written to ``OUT/table.md`` and ``OUT/table.json``,
followed by the issue's criteria checked on it, the trace plot to ``OUT/fidelity_trace.png``. With seeds, PSNR,
CVQ-AUC and CUC@20 show mean +- one seed sd.

The paper's spatial figure: full vs each ablation of the same seed, cell by cell (``eligsir_o3d.eval.spatial``), in
``OUT/spatial-<variant>[-s<seed>]/spatial_delta.png|json``; the per-cell figures (weakest deciles, cells improved by
more than 5 and 10 dB, cells made worse) follow the table, mean +- sd over the seeds.

Speed: ``--speed 1`` (default) replays the stream at its recorded rate, as the paper's online ablations run
(mapping time about the acquisition time: 89 s for the 87 s TUM sequence); ``--speed 0.1`` grants 10x the compute.
CUC@20 counts 0.5 m cells: with a few dozen evaluable cells one cell moves it by 1-2 points, so the table also gives
the cells at or above 20 dB and the evaluable cells.

Budget: by default the deterministic cost-model clock (``--budget cost``): frames are released at their
timestamps divided by ``--speed`` against *modelled* time (``CostModel``: seconds per update from supervised
pixels and Gaussians, seconds per frame), so every variant gets the same compute budget, reproducibly, and a variant
whose updates cost more gets fewer of them (and drops frames once its queue is full). ``--budget updates`` grants
every variant the same number of updates per frame instead; ``--realtime`` replays against the wall clock.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

VARIANTS = {"full": (), "fidelity": ("fidelity",), "growth": ("growth",), "scheduling": ("views",)}
LABELS = {"full": "EliGSiR", "fidelity": "w/o adaptive fidelity", "growth": "w/o targeted growth",
          "scheduling": "w/o view scheduling"}
COLUMNS = [("PSNR", "psnr", "{:.2f}"), ("CVQ-AUC", "cvq_auc", "{:.2f}"), ("CVQ-AUC common-p", "cvq_auc_common", "{:.2f}"),
           ("CUC@20 [%]", "cuc20", "{:.1f}"), ("cells >=20 / eval.", "cells", "{}"),
           ("Sup. px [M]", "supervised_mpix", "{:.1f}"),
           ("Gaus. [k]", "gaussians_k", "{:.1f}"), ("Map. time [s]", "mapping_time_s", "{:.1f}"),
           ("model time [s]", "modelled_time_s", "{:.1f}"), ("updates", "updates", "{:d}"),
           ("admitted", "frames_admitted", "{:d}"), ("dropped", "dropped_frames", "{:d}")]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("path", nargs="?", default="../shared/data/7scenes_redkitchen_jpg1000")
    p.add_argument("--out", default="runs/ablation")
    p.add_argument("--max-frames", type=int, default=300)
    p.add_argument("--holdout-every", type=int, default=8)
    p.add_argument("--variants", default="full,fidelity,growth,scheduling",
                   help="comma-separated subset of: " + ", ".join(VARIANTS))
    p.add_argument("--budget", choices=["cost", "updates"], default="cost")
    p.add_argument("--speed", type=float, default=1.0,
                   help="replay speed (1: the recorded rate, as the paper's online ablations; 0.1: 10x the compute)")
    p.add_argument("--updates-per-frame", type=int, default=None, help="--budget updates: updates per frame")
    p.add_argument("--realtime", action="store_true", help="replay against the wall clock instead")
    p.add_argument("--renderer", default="auto")
    p.add_argument("--device", default="cpu")
    p.add_argument("--eval-every", type=int, default=50, help="held-out checkpoint every N updates")
    p.add_argument("--drain", type=int, default=None, help="updates of the bounded drain (default: config's)")
    p.add_argument("--threads", type=int, default=None, help="torch/numba threads (1 is fastest on a busy CPU)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", default=None, metavar="S,S,...",
                   help="run every variant once per seed (OUT/<variant>-s<seed>); the table gives the means")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every variant, e.g. --set growth.min_views=3 (repeatable)")
    p.add_argument("--table-only", action="store_true", help="re-print the table from OUT/*/metrics.json")
    return p.parse_args(argv)


def seeds_of(args) -> list[int] | None:
    """The seeds of a multi-seed table, or None (one run per variant, ``--seed``, in ``OUT/<variant>``)."""
    if args.seeds is None:
        return None
    try:
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--seeds must be comma-separated integers, got {args.seeds!r}") from None
    if not seeds:
        raise SystemExit("--seeds names no seed")
    return seeds


def run_dir(out: Path, variant: str, seed: int | None) -> Path:
    return out / variant if seed is None else out / f"{variant}-s{seed}"


def make_config(args, variant: str, seed: int | None = None):
    from eligsir_o3d import Config
    from eligsir_o3d.config import apply_override

    cfg = Config(renderer=args.renderer, device=args.device, seed=args.seed if seed is None else seed,
                 ablate=VARIANTS[variant])
    cfg.clock.mode = "realtime" if args.realtime else args.budget
    cfg.clock.speed = args.speed
    if args.updates_per_frame is not None:
        cfg.clock.updates_per_frame = args.updates_per_frame
    if args.drain is not None:
        cfg.clock.drain_updates = args.drain
    for item in args.set:
        try:
            apply_override(cfg, item)
        except ValueError as e:
            raise SystemExit(str(e)) from None
    return cfg


def run_variant(args, variant: str, seed: int | None = None) -> dict:
    from eligsir_o3d.run.pipeline import run_mapping

    cfg = make_config(args, variant, seed)
    out = run_dir(Path(args.out), variant, seed)
    t0 = time.perf_counter()
    metrics = run_mapping(args.path, out, cfg, max_frames=args.max_frames, holdout_every=args.holdout_every,
                          eval_every=args.eval_every, progress=False)
    tag = variant if seed is None else f"{variant} seed {seed}"
    print(f"[{tag}] done in {time.perf_counter() - t0:.0f} s wall", flush=True)
    return metrics


def cell_counts(run: Path, threshold: float = 20.0) -> tuple[int, int] | None:
    """(cells with final PSNR >= ``threshold``, evaluable cells) from a results folder's cells.json: the two
    integers behind CUC@20 (with a few dozen cells, one cell is 1-2 points of it)."""
    f = run / "cells.json"
    if not f.is_file():
        return None
    cells = json.loads(f.read_text())
    ok = [q for q, e, m in zip(cells["q"], cells["eligible"], cells["measurable"]) if e and m and q is not None]
    return sum(q >= threshold for q in ok), len(ok)


def row(metrics: dict, run: Path | None = None) -> dict:
    held = metrics.get("heldout") or {}
    cuc = metrics.get("cuc20_final")
    counts = cell_counts(run) if run is not None else None
    return {"psnr": held.get("psnr"), "cvq_auc": metrics.get("cvq_auc"), "cuc20": None if cuc is None else 100 * cuc,
            "cells": None if counts is None else f"{counts[0]}/{counts[1]}",
            "supervised_mpix": metrics.get("supervised_mpix"), "gaussians_k": metrics.get("gaussians", 0) / 1e3,
            "mapping_time_s": metrics.get("mapping_time_s"), "modelled_time_s": metrics.get("modelled_time_s"),
            "updates": metrics.get("updates"),
            "frames_admitted": metrics.get("frames_admitted"), "dropped_frames": metrics.get("dropped_frames")}


def _curve_points(metrics: dict) -> tuple[list[float], list[float]]:
    """(progress, CVQ) of the checkpoints taken during acquisition; at equal progress the first one counts (the
    drain's checkpoint at p = 1 is a zero-width step in CVQ-AUC anyway)."""
    ps, cs = [], []
    for r in metrics.get("curve") or []:
        p, c = r.get("progress"), r.get("cvq")
        if p is None or c is None or (ps and p <= ps[-1]):
            continue
        ps.append(float(p))
        cs.append(float(c))
    return ps, cs


def _first_progress(metrics: dict) -> float:
    ps, _ = _curve_points(metrics)
    return ps[0] if ps else 0.0


def common_auc(metrics: dict, p0: float) -> float | None:
    """CVQ-AUC over the progress range every variant has checkpoints for ([p0, p_last]), linear in between.

    Checkpoints fall every N *updates*, so a variant with few (expensive) updates has its first checkpoint late and
    its plain CVQ-AUC skips the weak early phase; over a common range the variants compare like for like.
    """
    import numpy as np

    ps, cs = _curve_points(metrics)
    if not ps or ps[-1] <= p0:
        return None
    grid = np.linspace(p0, ps[-1], 256)
    return float(np.interp(grid, ps, cs).mean())


SPREAD_COLUMNS = ("psnr", "cvq_auc", "cuc20")  # shown with +- the seeds' sd


def spatial_figures(out: Path, variants: list[str], seeds: list[int] | None, results: dict) -> dict[str, dict]:
    """Per ablation variant: the cell-by-cell comparison with the full run of each seed (``OUT/spatial-<variant>
    [-s<seed>]``) and its figures' mean and sd over the seeds (``eligsir_o3d.eval.spatial.spatial_table``)."""
    from eligsir_o3d.eval.spatial import spatial_table

    pairs = {v: [(run_dir(out, "full", s), run_dir(out, v, s), out / (f"spatial-{v}" + ("" if s is None else f"-s{s}")))
                 for s in seeds or [None] if ("full", s) in results and (v, s) in results]
             for v in variants if v != "full"}
    return spatial_table(pairs)


def format_table(rows: dict[str, dict]) -> str:
    from eligsir_o3d.eval.spatial import plus_minus

    head = "| Variant | " + " | ".join(c[0] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for variant, r in rows.items():
        cells = []
        for _, key, fmt in COLUMNS:
            v = r.get(key)
            if v is None:
                cells.append("-")
            elif fmt == "{}":
                cells.append(str(v))
            elif key in SPREAD_COLUMNS:
                cells.append(plus_minus(float(v), r.get(key + "_sd"), fmt))
            else:
                cells.append(fmt.format(int(round(v)) if fmt == "{:d}" else float(v)))
        lines.append(f"| {LABELS.get(variant, variant)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mean_row(rows: list[dict]) -> dict:
    """Column means over one variant's seeds (the cell counts: summed, so the ratio is the pooled CUC@20)."""
    import numpy as np

    out = {}
    for key in rows[0]:
        vals = [r[key] for r in rows if r.get(key) is not None]
        if key == "cells":
            pairs = [tuple(int(x) for x in v.split("/")) for v in vals]
            out[key] = f"{sum(a for a, _ in pairs)}/{sum(b for _, b in pairs)}" if pairs else None
        else:
            out[key] = float(np.mean(vals)) if vals else None
            if vals and len(vals) > 1:
                out[key + "_sd"] = float(np.std(vals, ddof=1))
    return out


def criteria(rows: dict[str, dict], spatial: dict[str, dict] | None = None) -> list[str]:
    """Issue 16's Table III criteria, checked on the (mean) rows: the full method has the best held-out PSNR and
    CUC@20, and adaptive fidelity supervises >= 3x fewer pixels than fixed native resolution at no lower CVQ-AUC.
    Issue 30's, for view scheduling: PSNR and CUC@20 no lower than w/o view scheduling by more than one seed sd, the
    full method's weakest decile of cells higher, cells improved by more than 10 dB."""
    full = rows.get("full")
    if not full:
        return ["criteria: no full-method row"]
    from eligsir_o3d.eval.spatial import view_criteria

    lines = view_criteria(full, rows.get("scheduling"), ((spatial or {}).get("scheduling") or {}).get("spread"))
    for key, name in (("psnr", "held-out PSNR"), ("cuc20", "CUC@20")):
        others = {v: r.get(key) for v, r in rows.items() if v != "full" and r.get(key) is not None}
        if full.get(key) is None or not others:
            continue
        best = max(others, key=others.get)
        margin = full[key] - others[best]
        sd = full.get(key + "_sd")
        lines.append(f"full has the best {name}: {'yes' if margin >= 0 else 'NO'} ({full[key]:.2f} vs {LABELS[best]} "
                     f"{others[best]:.2f}, margin {margin:+.2f}" + (f", full's seed sd {sd:.2f})" if sd else ")"))
    fixed = rows.get("fidelity")
    if fixed and full.get("supervised_mpix") and fixed.get("supervised_mpix"):
        ratio = fixed["supervised_mpix"] / full["supervised_mpix"]
        auc_ok = (full.get("cvq_auc") or 0) >= (fixed.get("cvq_auc") or 0)
        lines.append(f"adaptive fidelity supervises {ratio:.2f}x fewer pixels than fixed native resolution "
                     f"(>= 3: {'yes' if ratio >= 3 else 'NO'}) at CVQ-AUC {full.get('cvq_auc'):.2f} vs "
                     f"{fixed.get('cvq_auc'):.2f} (no lower: {'yes' if auc_ok else 'NO'})")
    return lines


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.threads:
        os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
        import torch

        torch.set_num_threads(args.threads)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        print(f"unknown variant(s) {unknown}; choose from {', '.join(VARIANTS)}", file=sys.stderr)
        return 2
    seeds = seeds_of(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = [(v, s) for v in variants for s in (seeds or [None])]
    results: dict[tuple, dict] = {}
    for v, s in runs:
        f = run_dir(out, v, s) / "metrics.json"
        if args.table_only:
            if f.is_file():
                results[(v, s)] = json.loads(f.read_text())
        else:
            results[(v, s)] = run_variant(args, v, s)
    per_run = {k: row(m, run_dir(out, *k)) for k, m in results.items()}
    p0 = max([_first_progress(m) for m in results.values()] + [0.0])
    for k, m in results.items():
        per_run[k]["cvq_auc_common"] = common_auc(m, p0)
    rows = {v: mean_row([r for (rv, _), r in per_run.items() if rv == v]) for v in variants
            if any(rv == v for rv, _ in per_run)}
    from eligsir_o3d.eval.spatial import format_spatial

    table = format_table(rows)
    spatial = spatial_figures(out, variants, seeds, results)
    if spatial:
        table += "\n\nper-cell final PSNR, full vs each ablation (0.5 m cells evaluable in both):\n\n" + format_spatial(spatial, LABELS)
    if seeds:
        table = (f"means over seeds {', '.join(map(str, seeds))} (± one seed sd)\n\n{table}\n\nper run:\n\n"
                 + format_table({f"{v} s{s}": r for (v, s), r in per_run.items()}))
    checks = criteria(rows, spatial)
    cmd = "python tools/ablation.py " + " ".join(sys.argv[1:] if argv is None else argv)
    (out / "table.md").write_text(f"{cmd}\n\n{table}\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    (out / "table.json").write_text(json.dumps({"command": cmd, "rows": rows, "criteria": checks, "spatial": spatial,
                                                "runs": {f"{v}" + ("" if s is None else f"-s{s}"): r
                                                         for (v, s), r in per_run.items()}}, indent=1))
    from eligsir_o3d.eval.plots import fidelity_trace_plot
    from eligsir_o3d.run.results import read_fidelity_trace

    first = ("full", seeds[0] if seeds else None)
    trace = read_fidelity_trace(run_dir(out, *first)) if first in results else []
    fixed_curve = (results.get(("fidelity", first[1])) or {}).get("curve")  # fixed native resolution, same seed
    fig = fidelity_trace_plot(trace, out / "fidelity_trace.png", fixed_curve)
    print(table)
    for c in checks:
        print(c)
    if fig:
        print(f"fidelity trace: {fig}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
