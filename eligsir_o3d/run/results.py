"""The results folder of a run (ARCHITECTURE.md's contract): map.ply, trajectory.txt, config.json (the resolved
config), run.json (the sequence, the run options and the camera: with config.json, everything a rerun needs),
metrics.json (the summary a user reads), cells.json (the final per-cell table of the regional evaluation),
fidelity_trace.csv (Load-Adaptive Fidelity's decisions, one row per update), views_trace.csv (the view policy's
admissions, promotions, demotions and final replays per view) and plots. metrics.json names the
side files it comes with in ``files`` (read them with :func:`read_cells`, :func:`read_fidelity_trace`).

    eligsir map --rerun runs/kitchen --out runs/kitchen-again     # the same run again, from the folder alone
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from pathlib import Path

import numpy as np

from .options import RunOptions
from ..runtime.threads import report as threads_report

RUN_FILE = "run.json"  # read back by read_run
CELLS_FILE = "cells.json"
FIDELITY_TRACE_FILE = "fidelity_trace.csv"
VIEWS_TRACE_FILE = "views_trace.csv"  # the view policy's admissions, promotions, demotions (scheduling.views_trace)


@dataclasses.dataclass
class RunResult:
    """What a finished run hands the results writer (:func:`collect_metrics`, :func:`write_results`): exactly what
    the results folder holds. :meth:`~eligsir_o3d.run.pipeline.MappingPipeline.write` builds it."""

    out: Path  # the results folder
    sequence: str  # the sequence path as given
    opts: RunOptions  # run.json records them
    rec: object  # the Reconstructor: its map, config, camera, stats and policies
    report: object  # the clock's report: elapsed_s (modelled), released, integrated, dropped, skipped_bad
    clock: str  # the clock's name ("realtime": mapping time is the wall-clock time)
    frames_total: int
    frames_heldout: int
    frames_source: int
    map_state: str  # "ME", "+N PM", "offline-reference"
    pose_name: str  # the pose source metrics.json names
    tracked: bool  # poses came from a pose source (tracking), not from the recording
    cost_model_source: dict  # where the cost model came from ({} without one)
    final: dict  # the evaluator's final metrics of the evaluated map state (HeldoutEvaluator.final)
    accuracy: dict  # the tracked trajectory's accuracy against the ground truth ({} when not tracked or no truth)
    heldout_untracked: list | None  # held-out views tracked by the pose source ({"index", "reason"} each it could
    #                                 not track); None when the held-out views had their poses
    curve: list  # the evaluation checkpoints
    wall_s: float  # the mapper's wall-clock time (s), evaluation, decoding and checkpoint I/O excluded
    eval_s: float  # evaluation time (s)
    decode_s: float  # decoding time (s)
    acquisition_s: float  # the sequence's acquisition time (s), acquisition_time(seq, frames_total)
    skipped: list  # unreadable source frames
    heldout_skipped: list  # unreadable held-out frames
    trajectory: dict  # source index -> (timestamp, [4, 4] T_world_cam) of the mapped frames
    heldout_frames: list  # the held-out Frames (result pictures)
    render_heldout: object  # Frame -> render of the map at the held-out view's (evaluation) pose
    outputs: object  # the run's Outputs (a failed write is listed, the others go on)
    checkpoint_failures: list  # failed periodic checkpoints, {"next_source", "error"} each
    fidelity_trace: list | None  # the fidelity policy's decisions, a dict each (None: the policy keeps none)
    views_trace: list | None  # the view policy's events, a dict each (None: the policy keeps no trace)


def collect_metrics(r: RunResult) -> dict:
    """metrics.json of a finished run."""
    from ..budget.memory import peak_rss_mb
    from ..eval.tracked_heldout import heldout_pose_label

    rec, final, acc, report = r.rec, r.final, r.accuracy, r.report
    realtime = r.clock == "realtime"
    acq = r.acquisition_s
    if realtime:
        mapping_s = r.wall_s  # the mapper's elapsed wall-clock time: tracking included; decoding, evaluation excluded
    else:
        mapping_s = rec.stats.mapping_s + (rec.stats.tracking_s if r.tracked else 0.0)
    metrics = {
        "dataset": r.sequence,
        "frames_total": r.frames_total,
        "frames_heldout": r.frames_heldout,
        "frames_source": r.frames_source,
        "device": str(rec.device),
        "renderer": rec.config.renderer,
        "threads": threads_report(),
        "map_state": r.map_state,
        "pose_source": r.pose_name,
        "clock": r.clock,
        "cost_model": {**r.cost_model_source, "terms": rec.config.clock.cost.to_dict()}
        if r.cost_model_source.get("source") else None,
        "heldout": {k: final.get(k) for k in ("psnr", "ssim", "lpips", "depth_rmse_m", "depth_rmse_2m_m")},
        # where the held-out views' poses came from: the ground truth, or (a recording without poses) the run's pose
        # source, which tracked them without admitting them into the map; views it could not track are left out
        "heldout_pose_origin": heldout_pose_label(r.pose_name, r.heldout_untracked is not None),
        "heldout_untracked": list(r.heldout_untracked or []),
        # the rule "heldout" used: "given" (the map's frame is the given one); a tracked run's views are aligned
        # to the ground truth through its tracked poses ("aligned")
        "heldout_pose_rule": heldout_rule(r),
        # the figures of a pose-refined map, which this mapper does not make: kept null so that the keys of
        # metrics.json stay those results folders already have
        "heldout_given_poses": None,
        "heldout_by_pose_rule": None,
        "pose_refine": None,
        "cvq_auc": final.get("cvq_auc"),
        "cvq_final": final.get("cvq_final"),
        "cuc20_final": final.get("cuc20_final"),
        "mapping_time_s": mapping_s,
        "tracking_time_s": rec.stats.tracking_s,
        "ate_rmse_m": acc.get("ate_rmse_m"),
        "rpe_trans_m": acc.get("rpe_trans_m"),
        # loops found, accepted and rejected, and (with ground truth) the ATE of the tracker's poses and after
        "loop_closure": None if getattr(rec, "loops", None) is None else rec.loops.counters(),
        "wall_time_s": r.wall_s,
        # modelled seconds of the same work as mapping_time_s: the stream and the bounded drain
        "modelled_time_s": None if realtime else report.elapsed_s + report.drain_s,
        "cost_feedback_factor": None if realtime else report.cost_factor,
        "eval_time_s": r.eval_s,
        "decode_time_s": r.decode_s,
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
        "dropped_indices": list(report.dropped_indices),  # the source frames the full queue dropped
        "skipped_frames": list(r.skipped) + list(report.skipped_bad),
        "heldout_skipped": list(r.heldout_skipped),  # unreadable held-out frames: index, file, reason
        "peak_rss_mb": peak_rss_mb(),
        "curve": r.curve,
        "per_view": final.get("per_view"),
        # the side files written beside metrics.json (write_results): the cell table and the fidelity trace
        "files": {k: f for k, f, present in (("cells", CELLS_FILE, final.get("cells") is not None),
                                             ("fidelity_trace", FIDELITY_TRACE_FILE, bool(r.fidelity_trace)),
                                             ("views_trace", VIEWS_TRACE_FILE, r.views_trace is not None))
                  if present},
    }
    return metrics


def heldout_rule(r: RunResult) -> str:
    """The held-out pose rule of ``metrics["heldout"]`` (see :func:`collect_metrics`)."""
    if r.tracked:
        return "aligned" if r.accuracy else "tracked"
    return "given"


def write_results(r: RunResult, metrics: dict) -> None:
    """Write the results folder of run ``r`` (see the module docstring). Every file is written atomically; a
    file that cannot be written (full disk, I/O error) does not stop the others (:mod:`.safe_outputs`): metrics.json
    lists it, and a :class:`~.atomic_io.WriteFailed` naming it is raised at the end."""
    from ..io.atomic import atomic_write_text
    from ..eval import write_plots
    from ..pose.trajectory import write_tum_trajectory
    from ..export.web import parse_formats, write_web

    out, rec, outputs = r.out, r.rec, r.outputs
    outputs.stage(out / "map.ply", rec.save_ply, out / "map.ply")
    items = sorted(r.trajectory.items())
    web = parse_formats(r.opts.formats)[1:]
    if web:  # map.spz / map.splat beside map.ply, for web players (fixed 0.3 px^2): the map's low-pass baked in
        # once, at the depths the mapped views saw each Gaussian
        views = [T for _, (_, T) in items]
        for fmt in web:  # each on its own: a map SPZ cannot hold still gets its .splat
            outputs.optional(out / f"map.{fmt}", write_web, rec.gmap, camera=rec.camera, poses=views,
                             **{fmt: out / f"map.{fmt}"})
    outputs.stage(out / "trajectory.txt", write_tum_trajectory, out / "trajectory.txt",
                  [ts for _, (ts, _) in items], [T for _, (_, T) in items])
    outputs.stage(out / "config.json", rec.config.save, out / "config.json")
    if r.opts.pictures:
        from ..visual.run_pictures import write_result_pictures

        metrics["pictures"] = outputs.stage(out / "heldout", write_result_pictures, out, rec, r.heldout_frames,
                                            r.trajectory, render_heldout=r.render_heldout)
    cam = rec.camera
    run = {"sequence": r.sequence, "options": {f.name: getattr(r.opts, f.name) for f in dataclasses.fields(r.opts)
                                           if f.name not in ("resume", "progress", "view", "force_unlock",
                                                                             "overwrite")},
           "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                      "cy": cam.cy}}
    outputs.stage(out / RUN_FILE, atomic_write_text, out / RUN_FILE, json.dumps(jsonable(run), indent=2))
    outputs.stage(out / CELLS_FILE, write_side_files, out, r.final.get("cells"), r.fidelity_trace, r.views_trace)
    metrics["checkpoint_failures"] = r.checkpoint_failures
    metrics["write_failures"] = outputs.messages()  # what failed before metrics.json
    metrics["outputs_skipped"] = list(outputs.skipped)  # optional map formats this map cannot be written as
    outputs.stage(out / "metrics.json", atomic_write_text, out / "metrics.json",
                  json.dumps(jsonable(metrics), indent=1))
    if r.opts.plots:
        outputs.stage(out, write_plots, metrics, out, cells=r.final.get("cells"))
    outputs.finish(metrics)


def write_side_files(out: Path, cells: dict | None, trace: list[dict] | None,
                     views_trace: list[dict] | None = None) -> None:
    """cells.json (the final cell table, as :meth:`HeldoutEvaluator.final` returns it), fidelity_trace.csv
    (one row per recorded fidelity decision, a column per field) and views_trace.csv (the view policy's events),
    each only when there is data for it; all written atomically (a failed write leaves the previous file)."""
    from ..io.atomic import atomic_write_text

    if cells is not None:
        atomic_write_text(out / CELLS_FILE, json.dumps(jsonable(cells), separators=(",", ":")))
    for rows, name in ((trace, FIDELITY_TRACE_FILE), (views_trace, VIEWS_TRACE_FILE)):
        if rows:
            fields = list(dict.fromkeys(k for row in rows for k in row))
            buf = io.StringIO(newline="")
            w = csv.DictWriter(buf, fieldnames=fields)
            w.writeheader()
            w.writerows({k: "" if v is None else v for k, v in jsonable(row).items()} for row in rows)
            atomic_write_text(out / name, buf.getvalue())


def read_run(folder: str | Path):
    """(sequence path, Config, RunOptions) recorded in a results folder (its run.json and config.json), to run it
    again."""
    from ..config import Config

    folder = Path(folder)
    run_file, cfg_file = folder / RUN_FILE, folder / "config.json"
    for f in (run_file, cfg_file):
        if not f.is_file():
            raise ValueError(f"{folder}: no {f.name}: not a results folder written by this version of eligsir map")
    from ..io.inputs import read_json

    try:
        run = read_json(run_file, "run record")
        options = dict(run["options"])
        sequence = str(run["sequence"])
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{run_file}: not a valid run record ({e})") from None
    known = {f.name for f in dataclasses.fields(RunOptions)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"{run_file}: unknown run option(s) {unknown}")
    return sequence, Config.load(cfg_file), RunOptions(**options)


def _side_file(folder, key: str, default: str) -> Path:
    folder = Path(folder)
    from ..io.inputs import read_json

    try:
        name = (read_json(folder / "metrics.json", "metrics").get("files") or {}).get(key, default)
    except (ValueError, AttributeError):
        name = default
    if not isinstance(name, str) or Path(name).name != name:  # a name, never a path out of the folder
        name = default
    return folder / name


def read_cells(folder) -> dict | None:
    """The final cell table of a results folder (its cells.json), or None when the run wrote none."""
    path = _side_file(folder, "cells", CELLS_FILE)
    if not path.is_file():
        return None
    from ..io.inputs import read_json

    try:
        return read_json(path, "cell table")
    except ValueError as e:
        raise ValueError(f"{path}: not a readable cell table ({e})") from None


def read_fidelity_trace(folder) -> list[dict]:
    """The fidelity trace of a results folder (its fidelity_trace.csv) as a list of dicts of numbers (empty
    fields are None); [] when the run wrote none (e.g. the fidelity policy was ablated)."""
    path = _side_file(folder, "fidelity_trace", FIDELITY_TRACE_FILE)
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        try:
            return [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(f)]
        except (ValueError, csv.Error) as e:
            raise ValueError(f"{path}: not a readable fidelity trace ({e})") from None


def read_views_trace(folder) -> list[dict]:
    """The view policy's trace of a results folder (its views_trace.csv) as a list of dicts (numbers where the
    field is numeric, the ``event`` name as text); [] when the run wrote none."""
    path = _side_file(folder, "views_trace", VIEWS_TRACE_FILE)
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        try:
            return [{k: v if k == "event" else _number(v) for k, v in row.items()} for row in csv.DictReader(f)]
        except (ValueError, csv.Error) as e:
            raise ValueError(f"{path}: not a readable views trace ({e})") from None


def _number(text: str | None):
    if text is None or text == "":
        return None
    try:
        return int(text)
    except ValueError:
        return float(text)


def acquisition_time(seq, n: int) -> float:
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
