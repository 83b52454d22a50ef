"""Side-by-side table of several results folders (their metrics.json)."""

from __future__ import annotations

import math
from pathlib import Path

from ..io.inputs import read_json

# (row label, path into metrics.json, format); the first path that exists wins
ROWS = [
    ("map state", [("map_state",)], "s"),
    ("dataset", [("dataset",)], "s"),
    # the paper's rule first (given poses after one rigid training-pose alignment; a run without pose refinement:
    # its given poses), then the pose-refined run's figures under the other rules, labelled
    ("PSNR [dB] (paper's rule)", [("heldout_by_pose_rule", "aligned", "psnr"), ("heldout", "psnr")], ".2f"),
    ("PSNR in the map's refined frame (carried) [dB]", [("heldout_by_pose_rule", "carried", "psnr")], ".2f"),
    ("PSNR at given poses [dB]", [("heldout_given_poses", "psnr")], ".2f"),  # pose-refined runs only
    ("SSIM", [("heldout", "ssim")], ".3f"),
    ("LPIPS", [("heldout", "lpips")], ".3f"),
    ("depth RMSE [m]", [("heldout", "depth_rmse_m")], ".3f"),
    ("depth RMSE <=2m [m]", [("heldout", "depth_rmse_2m_m"), ("depth_rmse_2m_m",)], ".3f"),
    ("CVQ-AUC [dB]", [("cvq_auc",)], ".2f"),
    ("CVQ final [dB]", [("cvq_final",)], ".2f"),
    ("CUC@20 final [%]", [("cuc20_final",)], "pct"),
    ("updates", [("updates",)], "d"),
    ("supervised MPix", [("supervised_mpix",)], ".1f"),
    ("Gaussians", [("gaussians",)], "d"),
    ("mapping time [s]", [("mapping_time_s",)], ".1f"),
    ("RTF", [("rtf",)], ".2f"),
    ("dropped frames", [("dropped_frames",)], "d"),
]


def _get(d: dict, paths):
    for path in paths:
        cur = d
        for k in path:
            if not isinstance(cur, dict) or k not in cur:
                break
            cur = cur[k]
        else:
            return cur
    return None


def _fmt(v, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if fmt == "s":
        return str(v)
    if fmt == "pct":
        return f"{100.0 * float(v):.1f}"
    if fmt == "d":
        return f"{int(round(float(v))):d}"
    return format(float(v), fmt)


def _names(dirs: list[Path]) -> list[str]:
    """Short column names: the folder name, or more of the path where names collide."""
    names = [d.name or str(d) for d in dirs]
    if len(set(names)) < len(names):
        names = [str(d) for d in dirs]
    return names


def compare_results(dirs: list[Path]) -> str:
    """One text table: a row per metric, a column per results folder (reads ``<dir>/metrics.json``).

    Missing fields show as '-'. A folder without metrics.json raises FileNotFoundError naming it.
    """
    dirs = [Path(d) for d in dirs]
    if not dirs:
        raise ValueError("compare_results needs at least one results folder")
    runs = []
    for d in dirs:
        f = d / "metrics.json" if d.is_dir() or not d.suffix else d
        if not f.is_file():
            raise FileNotFoundError(f"{d}: no metrics.json (is it a results folder of `eligsir map`?)")
        try:  # a regular file, size-capped, nested a bounded depth
            m = read_json(f, "metrics.json")
        except ValueError as e:
            raise ValueError(f"{f}: not a valid metrics.json ({str(e).split(': ', 1)[-1]})") from None
        if not isinstance(m, dict):
            raise ValueError(f"{f}: not a valid metrics.json (a JSON {type(m).__name__}, not an object)")
        runs.append(m)
    header = ["metric"] + _names([d if d.is_dir() else d.parent for d in dirs])
    table = [header] + [[label] + [_fmt(_get(m, paths), fmt) for m in runs] for label, paths, fmt in ROWS]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]

    def line(row):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))

    rule = "  ".join("-" * w for w in widths)
    return "\n".join([line(header), rule] + [line(r) for r in table[1:]])
