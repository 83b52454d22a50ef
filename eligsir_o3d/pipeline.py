"""Offline driver: recorded sequence x pose source x clock x Reconstructor -> results folder.

It owns what the paper's protocol fixes around the mapper: the held-out split (never admitted into the map),
evaluation checkpoints every N updates (their time excluded from mapping time), the map state (ME or +N PM),
and the results-folder contract of ARCHITECTURE.md (map.ply, trajectory.txt, config.json, metrics.json, plots).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .config import Config
from .frame import Frame, FrameError

log = logging.getLogger("eligsir_o3d")


@dataclass
class RunOptions:
    max_frames: int | None = None
    sequence_options: dict | None = None  # passed to open_sequence (e.g. {"n_frames": 240} for the synthetic room)
    holdout_every: int = 8  # frames i with i % holdout_every == holdout_every // 2 are held out
    holdout_list: str | None = None  # a text file of frame indices to hold out instead
    pose: str = "gt"  # gt | odometry | kiss-icp | colmap | path to a TUM trajectory
    realtime: bool = False  # real-time replay against the wall clock instead of the deterministic budget
    speed: float = 1.0  # real-time replay speed factor
    eval_every: int = 100  # held-out checkpoint every N optimisation updates (0 = only at the end)
    eval_sample_stride: int = 2  # regional samples: every 2nd pixel in x and y of each held-out view
    eval_ssim_at_checkpoints: bool = True
    refine: int = 0  # +N post-mapping updates after the drain (map state "+N PM")
    offline_reference: bool = False  # all source frames available at once, long full-resolution schedule
    offline_updates: int = 0  # 0 -> 30 updates per source frame
    on_bad_frame: str = "skip"  # skip | stop
    checkpoint_every: int = 0  # frames between checkpoints (0 = none)
    resume: bool = False
    plots: bool = True
    progress: bool = True


def heldout_indices(n: int, every: int, listfile: str | None = None) -> list[int]:
    """The fixed evaluation split: every ``every``-th frame (offset every // 2), or the indices in ``listfile``."""
    if listfile:
        idx = sorted({int(tok) for tok in Path(listfile).read_text().split()})
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise ValueError(f"{listfile}: held-out indices {bad[:5]} outside 0..{n - 1}")
        return idx
    if every <= 0:
        return []
    return [i for i in range(n) if i % every == every // 2]


def run_mapping(path: str, out_dir: str | Path, config: Config | None = None, opts: RunOptions | None = None,
                **overrides) -> dict:
    """Map the sequence at ``path`` into ``out_dir``; returns the metrics dict also written as metrics.json."""
    from .datasets import open_sequence
    from .eval import HeldoutEvaluator, write_plots
    from .reconstructor import Reconstructor

    opts = opts or RunOptions()
    for k, v in overrides.items():
        if not hasattr(opts, k):
            raise TypeError(f"unknown run option {k!r}")
        setattr(opts, k, v)
    config = config or Config()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    seq = open_sequence(path, **(opts.sequence_options or {}))
    n = len(seq) if opts.max_frames is None else min(len(seq), int(opts.max_frames))
    if n == 0:
        raise ValueError(f"{path}: the sequence has no frames")
    held = heldout_indices(n, opts.holdout_every, opts.holdout_list)
    held_set = set(held)
    source = [i for i in range(n) if i not in held_set]
    if not source:
        raise ValueError(f"{path}: every frame is held out; nothing left to map")
    config.depth_scale = float(seq.depth_scale)
    pose_source = _pose_source(opts.pose, seq)

    log.info("loading %d held-out views", len(held))
    heldout_frames = [seq.frame(i, depth_max=config.depth_max) for i in held]
    evaluator = HeldoutEvaluator(heldout_frames, sample_stride=opts.eval_sample_stride,
                                 checkpoint_ssim=opts.eval_ssim_at_checkpoints)
    rec = Reconstructor(seq.camera, config.device, config)
    if opts.offline_reference:
        _offline_setup(rec, opts, len(source))

    def render_fn(frame: Frame):
        return rec.render(frame.T_world_cam, frame.camera)

    def checkpoint(r) -> None:
        evaluator.checkpoint(render_fn, t_s=r.stats.mapping_s, progress=r.stats.frames_released / len(source),
                             updates=r.stats.updates, supervised_mpix=r.stats.supervised_mpix, gaussians=len(r.gmap))

    def maybe_checkpoint(r) -> None:
        if opts.eval_every and r.stats.updates % opts.eval_every == 0:
            checkpoint(r)

    rec.callbacks.append(maybe_checkpoint)
    trajectory: dict[int, tuple[float, np.ndarray]] = {}

    def frames() -> Iterator[Frame]:
        for i in _progress(source, opts.progress, "mapping"):
            try:
                frame = seq.frame(i, depth_max=config.depth_max)
                if pose_source is not None:
                    t0 = time.perf_counter()
                    frame.T_world_cam = pose_source.track(i, frame.timestamp, frame.color, frame.depth, frame.camera)
                    rec.stats.tracking_s += time.perf_counter() - t0
            except (FrameError, ValueError, OSError) as e:
                if opts.on_bad_frame == "stop":
                    raise
                log.warning("skipping frame %d: %s", i, e)
                skipped.append(f"frame {i}: {e}")
                continue
            trajectory[i] = (frame.timestamp, frame.T_world_cam)
            yield frame

    skipped: list[str] = []
    clock = _clock(rec, opts, config)
    wall0 = time.perf_counter()
    report = clock.run(rec, frames(), on_release=evaluator.observe_source)
    if opts.offline_reference:
        rec.optimize(opts.offline_updates or 30 * len(source), scale=1.0)
        map_state = "offline-reference"
    else:
        rec.finalize()
        map_state = "ME"
    if opts.refine:
        rec.refine(opts.refine)
        map_state = f"+{opts.refine} PM" if not opts.offline_reference else map_state + f" +{opts.refine} PM"
    wall_s = time.perf_counter() - wall0 - rec.stats.excluded_s
    rec.callbacks.remove(maybe_checkpoint)
    checkpoint(rec)  # the curve ends at the evaluated map state (p = 1)
    final = evaluator.final(render_fn)

    rec.save_ply(out / "map.ply")
    _write_trajectory(out / "trajectory.txt", trajectory)
    config.save(out / "config.json")
    acq = _acquisition_time(seq, n)
    mapping_s = rec.stats.mapping_s + (rec.stats.tracking_s if pose_source is not None else 0.0)
    metrics = {
        "dataset": str(path),
        "frames_total": n,
        "frames_heldout": len(held),
        "frames_source": len(source),
        "device": str(rec.device),
        "renderer": rec.config.renderer,
        "map_state": map_state,
        "pose_source": opts.pose,
        "clock": clock.name,
        "heldout": {k: final.get(k) for k in ("psnr", "ssim", "lpips", "depth_rmse_m", "depth_rmse_2m_m")},
        "cvq_auc": final.get("cvq_auc"),
        "cvq_final": final.get("cvq_final"),
        "cuc20_final": final.get("cuc20_final"),
        "mapping_time_s": mapping_s,
        "tracking_time_s": rec.stats.tracking_s,
        "wall_time_s": wall_s,
        "eval_time_s": evaluator.eval_seconds,
        "acquisition_time_s": acq,
        "rtf": mapping_s / acq if acq > 0 else None,
        "updates": rec.stats.updates,
        "supervised_mpix": rec.stats.supervised_mpix,
        "gaussians": len(rec.gmap),
        "frames_released": report.released,
        "frames_admitted": rec.stats.frames_admitted,
        "dropped_frames": report.dropped,
        "skipped_frames": skipped + list(report.skipped_bad),
        "peak_rss_mb": _peak_rss_mb(),
        "curve": evaluator.curve,
        "cells": final.get("cells"),
        "per_view": final.get("per_view"),
    }
    trace = getattr(rec.fidelity, "trace", None)
    if trace:
        metrics["fidelity_trace"] = trace
    (out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=1))
    if opts.plots:
        write_plots(metrics, out)
    return metrics


def _pose_source(spec: str, seq):
    if spec == "gt":
        if seq.poses is None:
            raise ValueError(f"{seq.path}: the sequence has no ground-truth poses; choose --pose odometry|kiss-icp|colmap")
        return None
    from .pose import get_pose_source

    src = get_pose_source(spec, sequence=seq)
    src.prepare(seq)
    return src


def _clock(rec, opts: RunOptions, config: Config):
    from . import clock as clocks

    if opts.realtime:
        return clocks.RealtimeClock(speed=opts.speed, on_bad_frame=opts.on_bad_frame)
    if opts.offline_reference:
        return clocks.BudgetClock(0)
    return clocks.BudgetClock(config.optim.updates_per_frame)


def _offline_setup(rec, opts: RunOptions, n_source: int) -> None:
    """Offline reference: every source frame is retained and seeded, then one long full-resolution schedule."""
    from .scheduling.plain import FixedFidelity, NewSpaceSeeding, StrideConfig, StrideKeyframes

    rec.views = StrideKeyframes(StrideConfig(every=1, newest_fraction=0.0, max_views=max(n_source, 1)))
    rec.fidelity = FixedFidelity(1.0)
    rec.growth = NewSpaceSeeding(rec.config.seeding, seed=rec.config.seed)


def _acquisition_time(seq, n: int) -> float:
    ts = np.asarray(seq.timestamps[:n], dtype=np.float64)
    if len(ts) < 2:
        return 0.0
    return float(ts[-1] - ts[0] + (ts[-1] - ts[0]) / (len(ts) - 1))


def _write_trajectory(path: Path, trajectory: dict) -> None:
    from .camera import pose_to_tum

    lines = ["# timestamp tx ty tz qx qy qz qw (T_world_cam, camera-to-world)"]
    for i in sorted(trajectory):
        ts, T = trajectory[i]
        t, q = pose_to_tum(T)
        lines.append(f"{ts:.6f} " + " ".join(f"{x:.7f}" for x in (*t, *q)))
    path.write_text("\n".join(lines) + "\n")


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def _progress(items, enabled: bool, desc: str):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="frame", dynamic_ncols=True)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if hasattr(x, "item") and callable(x.item):
        return _jsonable(x.item())
    return x
