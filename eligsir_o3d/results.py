"""The results folder of a run (ARCHITECTURE.md's contract): map.ply, trajectory.txt, config.json (the resolved
config), run.json (the sequence, the run options and the camera: with config.json, everything a rerun needs),
metrics.json and plots.

    eligsir map --rerun runs/kitchen --out runs/kitchen-again     # the same run again, from the folder alone
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

RUN_FILE = "run.json"  # read back by pipeline.read_run


def collect_metrics(p) -> dict:
    """metrics.json of a finished :class:`~eligsir_o3d.pipeline.MappingPipeline` ``p``."""
    from .memory import peak_rss_mb

    rec, final, acc, report = p.rec, p.final, p.accuracy, p.report
    realtime = p.clock.name == "realtime"
    acq = _acquisition_time(p.seq, p.n)
    if realtime:
        mapping_s = p.wall_s  # the mapper's elapsed wall-clock time: tracking included; decoding, evaluation excluded
    else:
        mapping_s = rec.stats.mapping_s + (rec.stats.tracking_s if p.pose_source is not None else 0.0)
    metrics = {
        "dataset": p.path,
        "frames_total": p.n,
        "frames_heldout": len(p.held),
        "frames_source": len(p.source),
        "device": str(rec.device),
        "renderer": rec.config.renderer,
        "map_state": p.map_state,
        "pose_source": p.pose_name,
        "clock": p.clock.name,
        "cost_model": {**p.cost_model_source, "terms": rec.config.clock.cost.to_dict()}
        if p.cost_model_source.get("source") else None,
        "heldout": {k: final.get(k) for k in ("psnr", "ssim", "lpips", "depth_rmse_m", "depth_rmse_2m_m")},
        "cvq_auc": final.get("cvq_auc"),
        "cvq_final": final.get("cvq_final"),
        "cuc20_final": final.get("cuc20_final"),
        "mapping_time_s": mapping_s,
        "tracking_time_s": rec.stats.tracking_s,
        "ate_rmse_m": acc.get("ate_rmse_m"),
        "rpe_trans_m": acc.get("rpe_trans_m"),
        "wall_time_s": p.wall_s,
        "modelled_time_s": None if realtime else report.elapsed_s,
        "eval_time_s": p.evaluator.eval_seconds,
        "decode_time_s": p.decode_s,
        "acquisition_time_s": acq,
        "rtf": mapping_s / acq if acq > 0 else None,
        "updates": rec.stats.updates,
        "supervised_mpix": rec.stats.supervised_mpix,
        "gaussians": len(rec.gmap),
        "frames_released": report.released,
        "frames_admitted": rec.stats.frames_admitted,
        "policies": rec.policy_counters(),
        "stage_times": rec.timing.summary(max(1, report.integrated)),  # where the mapper's wall time went
        "dropped_frames": report.dropped,
        "skipped_frames": p.skipped + list(report.skipped_bad),
        "peak_rss_mb": peak_rss_mb(),
        "curve": p.evaluator.curve,
        "cells": final.get("cells"),
        "per_view": final.get("per_view"),
    }
    trace = getattr(rec.fidelity, "trace", None)
    if trace:
        metrics["fidelity_trace"] = trace
    return metrics


def write_results(p, metrics: dict) -> None:
    """Write the results folder of pipeline ``p`` (see the module docstring)."""
    from .eval import write_plots
    from .pose.trajectory import write_tum_trajectory

    out, rec = p.out, p.rec
    rec.save_ply(out / "map.ply")
    items = sorted(p.trajectory.items())
    write_tum_trajectory(out / "trajectory.txt", [ts for _, (ts, _) in items], [T for _, (_, T) in items])
    rec.config.save(out / "config.json")
    if p.opts.pictures:
        from .visual.results import write_result_pictures

        metrics["pictures"] = write_result_pictures(out, rec, p.heldout_frames, p.trajectory)
    cam = rec.camera
    run = {"sequence": p.path, "options": {f.name: getattr(p.opts, f.name) for f in dataclasses.fields(p.opts)
                                           if f.name not in ("resume", "progress", "view")},
           "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                      "cy": cam.cy}}
    (out / RUN_FILE).write_text(json.dumps(jsonable(run), indent=2))
    (out / "metrics.json").write_text(json.dumps(jsonable(metrics), indent=1))
    if p.opts.plots:
        write_plots(metrics, out)


def _acquisition_time(seq, n: int) -> float:
    ts = np.asarray(seq.timestamps[:n], dtype=np.float64)
    if len(ts) < 2:
        return 0.0
    return float(ts[-1] - ts[0] + (ts[-1] - ts[0]) / (len(ts) - 1))


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if hasattr(x, "item") and callable(x.item):
        return jsonable(x.item())
    return x
