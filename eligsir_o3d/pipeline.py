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
    speed: float | None = None  # replay speed (both clocks; None: config.clock.speed): 0.1 gives the mapper 10x
    eval_every: int = 100  # held-out checkpoint every N optimisation updates (0 = only at the end)
    eval_sample_stride: int = 2  # regional samples: every 2nd pixel in x and y of each held-out view
    eval_ssim_at_checkpoints: bool = True
    refine: int = 0  # +N post-mapping updates after the drain (map state "+N PM")
    offline_reference: bool = False  # all source frames available at once, long full-resolution schedule
    offline_updates: int = 0  # 0 -> 30 updates per source frame
    on_bad_frame: str | None = None  # skip | stop (None: config.clock.on_bad_frame)
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
    ck_path = out / "checkpoint.pt"
    start, trajectory, skipped = 0, {}, []
    if opts.resume and ck_path.is_file():
        from .checkpoint import load_checkpoint

        rec = load_checkpoint(ck_path, config.device, sequence=seq, pose_source=pose_source)
        extra = rec.checkpoint_extra or {}
        start = int(extra.get("next_source", 0))
        trajectory = {int(i): (float(ts), np.asarray(T, dtype=np.float64).reshape(4, 4))
                      for i, ts, T in extra.get("trajectory", [])}
        skipped = list(extra.get("skipped", []))
        evaluator.curve = list(extra.get("curve", []))
        log.info("resuming %s at source frame %d of %d", ck_path, start, len(source))
        for i in source[:start]:  # eligibility depends on the released source views, not on the mapper
            if i in trajectory:
                evaluator.observe_source(seq.frame(i, T_world_cam=trajectory[i][1], depth_max=config.depth_max))
    else:
        rec = Reconstructor(seq.camera, config.device, config)
    config = rec.config
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

    def save_state(next_source: int) -> None:
        t0 = time.perf_counter()
        extra = {"next_source": next_source, "skipped": skipped, "curve": evaluator.curve,
                 "trajectory": [[i, ts, T.reshape(-1).tolist()] for i, (ts, T) in sorted(trajectory.items())]}
        rec.save(ck_path, extra=extra, sequence=seq)
        rec.stats.excluded_s += time.perf_counter() - t0  # checkpoint I/O is not mapping time

    decode_s = [0.0]

    def frames() -> Iterator[Frame]:
        for k in _progress(range(start, len(source)), opts.progress, "mapping", len(source), start):
            if opts.checkpoint_every and k > start and k % opts.checkpoint_every == 0:
                save_state(k)  # every frame before k has been integrated by now
            i = source[k]
            try:
                t0 = time.perf_counter()
                try:
                    frame = seq.frame(i, depth_max=config.depth_max)
                finally:  # decoding the recording is the sensor's work, not the mapper's (a live camera delivers
                    dt = time.perf_counter() - t0  # decoded images): off the mapper's clock
                    decode_s[0] += dt
                    rec.stats.excluded_s += dt
                if pose_source is not None:
                    t0 = time.perf_counter()
                    # the first tracked frame is anchored at its ground-truth pose (when there is one), so the
                    # map lives in the ground truth's frame and the fixed held-out poses see it
                    anchor = seq.poses[i] if seq.poses is not None and not trajectory else None
                    frame.T_world_cam = pose_source.track(i, frame.timestamp, frame.color, frame.depth,
                                                          frame.camera, gt_pose=anchor)
                    rec.stats.tracking_s += time.perf_counter() - t0
            except (FrameError, ValueError, OSError, RuntimeError) as e:
                if config.clock.on_bad_frame == "stop":
                    raise
                msg = str(e) if str(e).startswith(f"frame {i}") else f"frame {i}: {e}"
                log.warning("skipping %s", msg)
                skipped.append(msg)
                continue
            trajectory[i] = (frame.timestamp, frame.T_world_cam)
            yield frame

    def on_release(frame: Frame) -> None:
        t0 = time.perf_counter()
        evaluator.observe_source(frame)  # evaluation bookkeeping (cell eligibility): not mapping time
        rec.stats.excluded_s += time.perf_counter() - t0

    clock = _clock(opts, config)
    rec.warmup()  # the renderer's one-time start-up cost is not paid by the stream's first frames
    wall0 = time.perf_counter()
    report = clock.run(rec, frames(), on_release=on_release)
    if opts.offline_reference:
        from .budget import offline_updates

        if opts.offline_updates:
            config.clock.offline_updates = opts.offline_updates
        rec.optimize(offline_updates(config.clock, len(source)), scale=1.0)
        map_state = "offline-reference"
    else:
        clock.drain(rec, _acquisition_time(seq, n))
        map_state = "ME"
    if opts.refine:
        rec.refine(opts.refine)
        map_state = f"+{opts.refine} PM" if not opts.offline_reference else map_state + f" +{opts.refine} PM"
    wall_s = time.perf_counter() - wall0 - rec.stats.excluded_s
    rec.callbacks.remove(maybe_checkpoint)
    checkpoint(rec)  # the curve ends at the evaluated map state (p = 1)
    accuracy = _trajectory_accuracy(seq, trajectory, out, opts) if pose_source is not None else {}
    if accuracy:
        # Evaluation poses stay the ground truth's; they are expressed in the map's frame through the
        # alignment of the tracked source poses to the ground truth (the paper's "training-pose alignment").
        T_est_gt = np.linalg.inv(_pose_alignment(seq, trajectory))
        for f in heldout_frames:
            f.T_world_cam = T_est_gt @ f.T_world_cam
    final = evaluator.final(render_fn)

    rec.save_ply(out / "map.ply")
    _write_trajectory(out / "trajectory.txt", trajectory)
    cam = rec.camera
    (out / "config.json").write_text(json.dumps({**config.to_dict(), "camera": {
        "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}}, indent=2))
    acq = _acquisition_time(seq, n)
    if clock.name == "realtime":
        mapping_s = wall_s  # the mapper's elapsed wall-clock time: tracking included; decoding, evaluation excluded
    else:
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
        "ate_rmse_m": accuracy.get("ate_rmse_m"),
        "rpe_trans_m": accuracy.get("rpe_trans_m"),
        "wall_time_s": wall_s,
        "modelled_time_s": report.elapsed_s if clock.name != "realtime" else None,
        "eval_time_s": evaluator.eval_seconds,
        "decode_time_s": decode_s[0],
        "acquisition_time_s": acq,
        "rtf": mapping_s / acq if acq > 0 else None,
        "updates": rec.stats.updates,
        "supervised_mpix": rec.stats.supervised_mpix,
        "gaussians": len(rec.gmap),
        "frames_released": report.released,
        "frames_admitted": rec.stats.frames_admitted,
        "policies": rec.policy_counters(),
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


def _clock(opts: RunOptions, config: Config):
    """The clock of this run: ``config.clock`` (options given to the run override it), or the offline reference's."""
    from .budget import get_clock

    if opts.on_bad_frame is not None:
        config.clock.on_bad_frame = opts.on_bad_frame
    if opts.speed is not None:
        config.clock.speed = opts.speed
    if opts.realtime:
        config.clock.mode = "realtime"
    return get_clock(config, offline=opts.offline_reference)


def _trajectory_accuracy(seq, trajectory: dict, out: Path, opts: RunOptions) -> dict:
    """ATE/RPE of the tracked source trajectory against the sequence's ground truth, and a top-view plot."""
    if seq.poses is None or len(trajectory) < 3:
        return {}
    from .pose import plot_trajectories, trajectory_accuracy

    est = {ts: T for ts, T in trajectory.values()}
    gt = {float(seq.timestamps[i]): seq.poses[i] for i in trajectory}
    acc = trajectory_accuracy(est, gt, return_alignment=True)
    if opts.plots:
        plot_trajectories(out / "trajectory_topview.png", {"gt": gt, opts.pose: est}, reference="gt",
                          title=f"ATE {acc['ate_rmse_m'] * 100:.2f} cm")
    return acc


def _pose_alignment(seq, trajectory: dict) -> np.ndarray:
    """T_gt_est from whole poses: rotation = SVD projection of sum_i R_gt,i R_est,i^T, then mean translation.

    Unlike a positions-only (Umeyama) fit, this stays well conditioned on short, nearly straight trajectories,
    where many rotations explain the camera centres equally well but disagree on where the cameras look.
    """
    P = np.stack([T for _, T in trajectory.values()])
    Q = np.stack([seq.poses[i] for i in trajectory])
    M = np.einsum("nij,nkj->ik", Q[:, :3, :3], P[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (Q[:, :3, 3] - P[:, :3, 3] @ R.T).mean(0)
    return T


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


def _progress(items, enabled: bool, desc: str, total: int | None = None, initial: int = 0):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="frame", dynamic_ncols=True, total=total, initial=initial)


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
