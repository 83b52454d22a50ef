"""The paper's "Spatial effect of Map-Guided View Scheduling": per-cell quality of two runs of one sequence.

Two results folders of the same sequence and held-out split (typically the full method A and an ablation B) share
the regional evaluation's cells (``cells.json``: 0.5 m world cubes, final cell PSNR q_c). Over the cells evaluable in
both (eligible and measurable, finite q_c) this module computes

- delta_c = q_c(A) - q_c(B) per cell, with mean and median of both runs and of the deltas;
- the weakest decile of cells under B (the ceil(10 %) lowest q_c(B)) and what A makes of the same cells, and each
  run's own weakest decile (the fair comparison: picking cells by B's low values favours A by regression to the mean);
- the count of cells improved by more than 5 and 10 dB, and the count made worse (delta_c < 0; and < -5 dB);

and draws the figure: A, B and delta top-down on the cell grid (each map pixel a column of cells along the up axis,
coloured by the column mean). Counts are per 3D cell, not per column.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

AXES = "xyz"
DECILE = 0.1


def evaluable(cells: dict) -> dict[tuple, float]:
    """{cell key (3 ints): final q_c [dB]} of the evaluable cells of a cell table (a results folder's cells.json)."""
    for field in ("keys", "q", "eligible", "measurable", "cell_size"):
        if field not in cells:
            raise ValueError(f"cell table has no {field!r} field (is it a results folder's cells.json?)")
    out = {}
    for k, q, e, m in zip(cells["keys"], cells["q"], cells["eligible"], cells["measurable"]):
        if e and m and q is not None and math.isfinite(float(q)):
            out[tuple(int(x) for x in k)] = float(q)
    return out


def _decile(values: np.ndarray) -> np.ndarray:
    """Indices of the ceil(10 %) lowest values (at least one) of ``values`` [n]; stable on ties."""
    n = max(1, int(math.ceil(DECILE * len(values))))
    return np.argsort(values, kind="stable")[:n]


def cell_deltas(cells_a: dict, cells_b: dict) -> dict:
    """Per-cell comparison of two cell tables over the cells evaluable in both (see the module docstring).

    Returns a JSON-ready dict: ``keys`` [n, 3], ``q_a``, ``q_b``, ``delta`` [n] (dB, A - B) and the summary figures.
    Raises ValueError when the tables use different cell sizes.
    """
    qa, qb = evaluable(cells_a), evaluable(cells_b)
    if float(cells_a["cell_size"]) != float(cells_b["cell_size"]):
        raise ValueError(f"cell sizes differ: {cells_a['cell_size']} vs {cells_b['cell_size']} m")
    keys = sorted(set(qa) & set(qb))
    a = np.array([qa[k] for k in keys], dtype=np.float64)
    b = np.array([qb[k] for k in keys], dtype=np.float64)
    d = a - b
    out = {"cell_size": float(cells_a["cell_size"]), "up_axis": int(cells_a.get("up_axis", 2)),
           "n_common": len(keys), "n_only_a": len(set(qa) - set(qb)), "n_only_b": len(set(qb) - set(qa)),
           "keys": [list(k) for k in keys], "q_a": a.round(4).tolist(), "q_b": b.round(4).tolist(),
           "delta": d.round(4).tolist()}
    if not keys:
        return {**out, "summary": None}
    weak_b, weak_a = _decile(b), _decile(a)
    out["summary"] = {
        "mean_a": float(a.mean()), "mean_b": float(b.mean()),
        "median_a": float(np.median(a)), "median_b": float(np.median(b)),
        "mean_delta": float(d.mean()), "median_delta": float(np.median(d)),
        "decile_cells": int(len(weak_b)),
        # B's weakest decile and what A makes of the same cells
        "weak_b_under_b": float(b[weak_b].mean()), "weak_b_under_a": float(a[weak_b].mean()),
        # each run's own weakest decile (its 10 % lowest cells, whichever they are)
        "own_decile_a": float(a[weak_a].mean()), "own_decile_b": float(b[weak_b].mean()),
        "improved_5db": int((d > 5).sum()), "improved_10db": int((d > 10).sum()),
        "worse": int((d < 0).sum()), "worse_5db": int((d < -5).sum()),
        "max_delta": float(d.max()), "min_delta": float(d.min()),
    }
    return out


def _columns(keys: np.ndarray, values: np.ndarray, up: int):
    """Top-down grid [rows, cols] of column means of ``values`` [n] at cell ``keys`` [n, 3]; NaN where empty."""
    a, b = [i for i in range(3) if i != up]
    ka, kb = keys[:, a], keys[:, b]
    a0, b0 = ka.min(), kb.min()
    shape = (kb.max() - b0 + 1, ka.max() - a0 + 1)
    total, count = np.zeros(shape), np.zeros(shape)
    np.add.at(total, (kb - b0, ka - a0), values)
    np.add.at(count, (kb - b0, ka - a0), 1)
    grid = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return grid, (a0, ka.max() + 1, b0, kb.max() + 1), (a, b)


def plot_deltas(result: dict, path: Path, label_a: str = "full", label_b: str = "ablation") -> Path:
    """Three top-down panels (A, B, A - B) of :func:`cell_deltas`'s result, written as a PNG to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    s = result.get("summary")
    if result["n_common"]:
        keys = np.asarray(result["keys"], dtype=np.int64).reshape(-1, 3)
        size, up = result["cell_size"], result["up_axis"]
        qa, qb, d = (np.asarray(result[k], dtype=np.float64) for k in ("q_a", "q_b", "delta"))
        grids = [_columns(keys, v, up) for v in (qa, qb, d)]
        shown = np.concatenate([g[np.isfinite(g)] for g, _, _ in grids[:2]])
        lo, hi = float(np.percentile(shown, 2)), float(np.percentile(shown, 98))  # of the column means shown
        span = max(1.0, float(np.nanmax(np.abs(grids[2][0]))))
        titles = [f"{label_a}\nmean {s['mean_a']:.2f}, median {s['median_a']:.2f} dB",
                  f"{label_b}\nmean {s['mean_b']:.2f}, median {s['median_b']:.2f} dB",
                  f"delta = {label_a} - {label_b}\n{s['improved_10db']} cells > +10 dB, {s['improved_5db']} > +5, "
                  f"{s['worse']} worse"]
        for ax, (grid, ext, (ia, ib)), title, (cmap, vmin, vmax) in zip(
                axes, grids, titles, [("RdYlGn", lo, hi), ("RdYlGn", lo, hi), ("RdBu", -span, span)]):
            extent = tuple(float(x) * size for x in ext)
            im = ax.imshow(grid, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax,
                           interpolation="nearest")
            fig.colorbar(im, ax=ax, label="dB (column mean)", shrink=0.85)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel(f"{AXES[ia]} [m]")
            ax.set_ylabel(f"{AXES[ib]} [m]")
            ax.set_aspect("equal")
    fig.suptitle(f"Per-cell final PSNR over {result['n_common']} cells evaluable in both runs "
                 f"({result['cell_size']:g} m cells, top-down; a pixel is the mean of its column of cells)", fontsize=11)
    fig.tight_layout()
    from ..io.atomic import atomic_write

    path = Path(path)
    try:
        atomic_write(path, lambda f: fig.savefig(f, dpi=120, format="png"))
    finally:
        plt.close(fig)
    return path


def _read_run(folder: Path) -> tuple[dict, dict]:
    from ..run.results import read_cells

    folder = Path(folder)
    f = folder / "metrics.json"
    if not f.is_file():
        raise FileNotFoundError(f"{folder}: no metrics.json (is it a results folder of `eligsir map`?)")
    cells = read_cells(folder)
    if cells is None:
        raise FileNotFoundError(f"{folder}: no cells.json (the run wrote no regional evaluation)")
    from ..io.inputs import read_json

    return read_json(f, "metrics.json"), cells


def compare_spatial(dir_a, dir_b, out_dir=None, stem: str = "spatial_delta") -> dict:
    """Compare two results folders of one sequence cell by cell; write ``<stem>.json`` and ``<stem>.png`` into
    ``out_dir`` (default: ``dir_a``). Raises ValueError when the folders hold different sequences or splits."""
    ma, ca = _read_run(dir_a)
    mb, cb = _read_run(dir_b)
    same = {"dataset": lambda m: Path(str(m.get("dataset"))).name,  # the runs may name it from different folders
            "frames_total": lambda m: m.get("frames_total"), "frames_heldout": lambda m: m.get("frames_heldout")}
    for key, get in same.items():
        if get(ma) != get(mb):
            raise ValueError(f"{dir_a} and {dir_b} are not runs of the same sequence and split: "
                             f"{key} {ma.get(key)!r} vs {mb.get(key)!r}")
    from ..io.atomic import atomic_write_text, write_failed
    from ..io.outputs import check_output_folder

    result = {"a": str(dir_a), "b": str(dir_b), **cell_deltas(ca, cb)}
    out = Path(out_dir) if out_dir is not None else Path(dir_a)
    check_output_folder(out, "--spatial-out")  # a file there: WriteFailed, exit 3
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise write_failed(out, e) from None
    atomic_write_text(out / f"{stem}.json", json.dumps(result, indent=1))
    result["png"] = str(plot_deltas(result, out / f"{stem}.png", Path(dir_a).name, Path(dir_b).name))
    return result


def format_summary(result: dict) -> str:
    """A few lines of text for the terminal (``eligsir eval A B``)."""
    s = result.get("summary")
    if not s:
        return f"per-cell comparison: no cell evaluable in both runs ({result['a']} vs {result['b']})"
    return "\n".join([
        f"per-cell final PSNR over {result['n_common']} common cells ({result['cell_size']:g} m), A = {result['a']}, "
        f"B = {result['b']}:",
        f"  mean A {s['mean_a']:.2f} / B {s['mean_b']:.2f} dB, median A {s['median_a']:.2f} / B {s['median_b']:.2f} dB",
        f"  B's weakest decile ({s['decile_cells']} cells): {s['weak_b_under_b']:.2f} dB under B, "
        f"{s['weak_b_under_a']:.2f} under A; own weakest decile A {s['own_decile_a']:.2f} / B {s['own_decile_b']:.2f}",
        f"  cells improved by > 5 dB: {s['improved_5db']}, > 10 dB: {s['improved_10db']}; worse: {s['worse']} "
        f"(< -5 dB: {s['worse_5db']}); delta range {s['min_delta']:+.2f} .. {s['max_delta']:+.2f} dB",
        f"  figure: {result.get('png')}",
    ])


SPREAD_KEYS = ("n_common", "mean_delta", "weak_b_under_b", "weak_b_under_a", "own_decile_a", "own_decile_b",
               "improved_5db", "improved_10db", "worse", "worse_5db", "max_delta")


def spread(results: list[dict]) -> dict:
    """{figure: (mean, sd)} of :func:`cell_deltas` summaries over several seeds (sd None with one seed; seeds
    without common cells are skipped)."""
    summaries = [dict(r["summary"], n_common=r["n_common"]) for r in results if r.get("summary")]
    out = {}
    for key in SPREAD_KEYS:
        vals = np.array([s[key] for s in summaries], dtype=np.float64)
        if len(vals):
            out[key] = (float(vals.mean()), float(vals.std(ddof=1)) if len(vals) > 1 else None)
    return out


def spatial_table(pairs: dict[str, list[tuple]]) -> dict[str, dict]:
    """{variant: [(folder A, folder B, output folder), ...]} (one triple per seed) -> {variant: {"spread":
    :func:`spread` over the seeds, "png": the figures}}; a pair that cannot be compared is reported and skipped."""
    table = {}
    for v, triples in pairs.items():
        done = []
        for a, b, folder in triples:
            try:
                done.append(compare_spatial(a, b, folder))
            except (ValueError, FileNotFoundError) as e:
                print(f"no per-cell comparison of {a} and {b}: {e}")
        if done:
            table[v] = {"spread": spread(done), "png": [r["png"] for r in done]}
    return table


def view_criteria(full: dict, abl: dict | None, sp: dict | None) -> list[str]:
    """The view-scheduling checks on Table III rows (means with ``<key>_sd``) and :func:`spread` of full vs w/o view scheduling:
    PSNR and CUC@20 no lower by more than one seed sd, full's own weakest decile higher, cells > 10 dB."""
    lines = []
    for key, name in (("psnr", "held-out PSNR"), ("cuc20", "CUC@20")) if abl else ():
        if full.get(key) is None or abl.get(key) is None:
            continue
        sd = max(full.get(key + "_sd") or 0.0, abl.get(key + "_sd") or 0.0)
        margin = full[key] - abl[key]
        lines.append(f"full's {name} no lower than w/o view scheduling by more than one seed sd: "
                     f"{'yes' if margin >= -sd else 'NO'} (margin {margin:+.2f}, sd {sd:.2f})")
    sp = sp or {}
    if "own_decile_a" in sp:
        a, b = sp["own_decile_a"][0], sp["own_decile_b"][0]
        lines.append(f"full's weakest decile of cells higher than w/o view scheduling's: {'yes' if a > b else 'NO'} "
                     f"({a:.2f} vs {b:.2f} dB; the ablation's weakest cells under full: {sp['weak_b_under_a'][0]:.2f} "
                     f"vs {sp['weak_b_under_b'][0]:.2f} dB)")
        lines.append(f"cells improved by more than 10 dB: {sp['improved_10db'][0]:.1f} per seed "
                     f"(> 5 dB: {sp['improved_5db'][0]:.1f}, worse: {sp['worse'][0]:.1f} of {sp['n_common'][0]:.0f})")
    return lines


SPATIAL_COLUMNS = [("cells", "n_common", "{:.0f}"), ("own weakest decile full [dB]", "own_decile_a", "{:.2f}"),
                   ("own weakest decile abl. [dB]", "own_decile_b", "{:.2f}"),
                   ("abl. weakest decile: abl. / full [dB]", ("weak_b_under_b", "weak_b_under_a"), "{:.2f}"),
                   ("cells > +5 dB", "improved_5db", "{:.1f}"), ("cells > +10 dB", "improved_10db", "{:.1f}"),
                   ("cells worse", "worse", "{:.1f}"), ("max delta [dB]", "max_delta", "{:.1f}")]


def plus_minus(value, sd, fmt: str) -> str:
    """``value`` formatted, with `` ± sd`` when an sd is given."""
    return fmt.format(value) + ("" if sd is None else " ± " + fmt.format(sd))


def format_spatial(table: dict[str, dict], labels: dict | None = None) -> str:
    """Markdown table, a row per ablation: ``table`` maps a variant to {"spread": :func:`spread`'s result}."""
    head = "| full vs | " + " | ".join(c[0] for c in SPATIAL_COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(SPATIAL_COLUMNS) + 1)]
    for v, t in table.items():
        sp, cells = t["spread"], []
        for _, key, fmt in SPATIAL_COLUMNS:
            keys = key if isinstance(key, tuple) else (key,)
            cells.append(" / ".join(plus_minus(*sp[k], fmt) if k in sp else "-" for k in keys))
        lines.append(f"| {(labels or {}).get(v, v)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
