"""The paper's Table III for one sequence, from the results folders of ``eligsir ablate``: the full method and each
ablation under the same held-out split and budget, plus the Load-Adaptive Fidelity trace (the paper's Fig. 6).

Variants: ``full`` (EliGSiR) and one per ``--ablate`` value: ``fidelity`` (fixed native resolution), ``growth``
(dense per-frame depth insertion), ``views`` (fixed-stride keyframes, uniform replay). Each variant's run is in
``OUT/<variant>`` (with seeds: ``OUT/<variant>-s<seed>``, and the table holds each variant's mean over the seeds,
+- one seed sd for PSNR, CVQ-AUC and CUC@20, with one row per run below). :func:`write_table` writes
``OUT/table.md``, ``OUT/table.json`` and ``OUT/fidelity_trace.png``.

The spatial comparison: full vs each ablation of the same seed, cell by cell (:mod:`.spatial`), in
``OUT/spatial-<variant>[-s<seed>]/spatial_delta.png|json``. CUC@20 counts 0.5 m cells: with a few dozen evaluable
cells one cell moves it by 1-2 points, so the table also gives the cells at or above 20 dB and the evaluable cells.
"""

from __future__ import annotations

import json
from pathlib import Path

VARIANTS = {"full": (), "fidelity": ("fidelity",), "growth": ("growth",), "views": ("views",)}
LABELS = {"full": "EliGSiR", "fidelity": "w/o adaptive fidelity", "growth": "w/o targeted growth",
          "views": "w/o view scheduling"}
COLUMNS = [("PSNR", "psnr", "{:.2f}"), ("CVQ-AUC", "cvq_auc", "{:.2f}"), ("CVQ-AUC common-p", "cvq_auc_common", "{:.2f}"),
           ("CUC@20 [%]", "cuc20", "{:.1f}"), ("cells >=20 / eval.", "cells", "{}"),
           ("Sup. px [M]", "supervised_mpix", "{:.1f}"),
           ("Gaus. [k]", "gaussians_k", "{:.1f}"), ("Map. time [s]", "mapping_time_s", "{:.1f}"),
           ("model time [s]", "modelled_time_s", "{:.1f}"), ("updates", "updates", "{:d}"),
           ("admitted", "frames_admitted", "{:d}"), ("dropped", "dropped_frames", "{:d}")]



def run_dir(out: Path, variant: str, seed: int | None) -> Path:
    """A variant's results folder: ``OUT/<variant>``, or ``OUT/<variant>-s<seed>`` with seeds."""
    return out / variant if seed is None else out / f"{variant}-s{seed}"


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
    from .spatial import spatial_table

    pairs = {v: [(run_dir(out, "full", s), run_dir(out, v, s), out / (f"spatial-{v}" + ("" if s is None else f"-s{s}")))
                 for s in seeds or [None] if ("full", s) in results and (v, s) in results]
             for v in variants if v != "full"}
    return spatial_table(pairs)


def format_table(rows: dict[str, dict]) -> str:
    from .spatial import plus_minus

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
    """The paper's claims for Table III, checked on the (mean) rows: the full method has the best held-out PSNR and
    CUC@20, and adaptive fidelity supervises >= 3x fewer pixels than fixed native resolution at no lower CVQ-AUC.
    For view scheduling: PSNR and CUC@20 no lower than w/o view scheduling by more than one seed sd, the full
    method's weakest decile of cells higher, cells improved by more than 10 dB."""
    full = rows.get("full")
    if not full:
        return ["criteria: no full-method row"]
    from .spatial import view_criteria

    lines = view_criteria(full, rows.get("views"), ((spatial or {}).get("views") or {}).get("spread"))
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


def write_table(out: Path, variants: list[str], seeds: list[int] | None, command: str) -> tuple[str, list[str], Path | None]:
    """Read each variant's ``metrics.json`` under ``out``, write table.md, table.json and the fidelity trace figure;
    returns (the table as text, the criteria lines, the figure or None)."""
    from .plots import fidelity_trace_plot
    from .spatial import format_spatial
    from ..run.results import read_fidelity_trace

    results = {(v, s): json.loads((run_dir(out, v, s) / "metrics.json").read_text())
               for v in variants for s in (seeds or [None]) if (run_dir(out, v, s) / "metrics.json").is_file()}
    per_run = {k: row(m, run_dir(out, *k)) for k, m in results.items()}
    p0 = max([_first_progress(m) for m in results.values()] + [0.0])
    for k, m in results.items():
        per_run[k]["cvq_auc_common"] = common_auc(m, p0)
    rows = {v: mean_row([r for (rv, _), r in per_run.items() if rv == v]) for v in variants
            if any(rv == v for rv, _ in per_run)}
    table = format_table(rows)
    spatial = spatial_figures(out, variants, seeds, results)
    if spatial:
        table += ("\n\nper-cell final PSNR, full vs each ablation (0.5 m cells evaluable in both):\n\n"
                  + format_spatial(spatial, LABELS))
    if seeds:
        table = (f"means over seeds {', '.join(map(str, seeds))} (± one seed sd)\n\n{table}\n\nper run:\n\n"
                 + format_table({f"{v} s{s}": r for (v, s), r in per_run.items()}))
    checks = criteria(rows, spatial)
    (out / "table.md").write_text(f"{command}\n\n{table}\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    (out / "table.json").write_text(json.dumps({"command": command, "rows": rows, "criteria": checks,
                                                "spatial": spatial,
                                                "runs": {f"{v}" + ("" if s is None else f"-s{s}"): r
                                                         for (v, s), r in per_run.items()}}, indent=1))
    first = ("full", seeds[0] if seeds else None)
    trace = read_fidelity_trace(run_dir(out, *first)) if first in results else []
    fixed_curve = (results.get(("fidelity", first[1])) or {}).get("curve")  # fixed native resolution, same seed
    return table, checks, fidelity_trace_plot(trace, out / "fidelity_trace.png", fixed_curve)
