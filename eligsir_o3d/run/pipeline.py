"""Offline driver: recorded sequence x pose source x clock x Reconstructor -> results folder.

It owns what the paper's protocol fixes around the mapper: the held-out split (never admitted into the map),
evaluation checkpoints every N updates (their time excluded from mapping time), the map state (ME or +N PM),
and the results folder (:mod:`.results`). :class:`MappingPipeline` reads as its steps:

    open -> build -> stream -> drain -> evaluate -> write
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..config import Config
from ..core.frame import Frame
from .cost_source import CALIBRATION_FRAMES, run_cost_model  # noqa: F401 (CALIBRATION_FRAMES: its old home)
from .frame_faults import BAD_FRAME_ERRORS, frame_fault
from .lock import RunLock
from .options import RunOptions
from .option_table import check_options, check_speed_for
from .outputs import Outputs, PeriodicCheckpoints
from .poses import loop_closed, pose_source_name, prepare_pose_source, trajectory_accuracy_of
from .results import read_run  # noqa: F401 (its old home: run.json is read where it is written)
from .resume import apply_new_settings, check_resume, run_record

__all__ = ["MappingPipeline", "RunOptions", "heldout_indices", "read_run", "run_mapping"]

log = logging.getLogger("eligsir_o3d")




def heldout_indices(n: int, every: int, listfile: str | None = None) -> list[int]:
    """The fixed evaluation split: every ``every``-th frame (offset every // 2), or the indices in ``listfile``."""
    if listfile:
        from ..io.inputs import printable, read_text

        toks = read_text(listfile, "held-out list").split()  # a regular file, size-capped
        bad_tok = next((t for t in toks if not t.isdigit() or len(t) > 12), None)
        if bad_tok is not None:
            raise ValueError(f"{printable(listfile)}: {printable(bad_tok)[:40]!r} is not a frame index (one "
                             f"non-negative integer per entry)")
        idx = sorted({int(tok) for tok in toks})
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise ValueError(f"{listfile}: held-out indices {bad[:5]} outside 0..{n - 1}")
        return idx
    if every < 0:
        raise ValueError(f"--holdout-every must be >= 0 (0: no held-out frames), got {every}")
    if every == 0:
        return []
    return [i for i in range(n) if i % every == every // 2]


def run_mapping(path: str, out_dir: str | Path, config: Config | None = None, opts: RunOptions | None = None,
                **overrides: Any) -> dict:
    """Map the sequence at ``path`` into ``out_dir`` by the paper's protocol, as ``eligsir map`` does.

    Args:
        path: anything :func:`~eligsir_o3d.datasets.open_sequence` opens (``"synthetic"`` included).
        out_dir: the results folder (``map.ply``, ``metrics.json``, ``trajectory.txt``, ``config.json``, ...).
        config: the mapper's configuration (default: ``Config()``, its shipped cost model).
        opts: how the sequence is run (frames, held-out split, pose source, outputs); default ``RunOptions()``.
        **overrides: :class:`RunOptions` fields set on ``opts``, e.g. ``max_frames=50``.

    Returns:
        The metrics dict, also written as ``metrics.json`` (``heldout``, ``cvq_auc``, ``updates``, ...).

    Raises:
        TypeError: an override that is not a RunOptions field.

    Example:
        ```python
        from eligsir_o3d.run.pipeline import run_mapping

        m = run_mapping("synthetic", "runs/api-room", max_frames=6, eval_every=0, plots=False, pictures=False,
                        sequence_options={"n_frames": 6, "width": 160, "height": 120})
        print(m["frames_total"], m["heldout"]["psnr"] > 0)  # 6 True
        ```
    """
    opts = opts or RunOptions()
    for k, v in overrides.items():
        if not hasattr(opts, k):
            raise TypeError(f"unknown run option {k!r}")
        setattr(opts, k, v)
    return MappingPipeline(path, out_dir, config, opts).run()


class MappingPipeline:
    """One run of the paper's protocol on a recorded sequence; :meth:`run` performs the labelled steps."""

    def __init__(self, path: str, out_dir: str | Path, config: Config | None = None, opts: RunOptions | None = None):
        self.path, self.out = str(path), Path(out_dir)
        self.opts = opts or RunOptions()
        check_options(self.opts)  # the run-options table: a value no run can use is one line naming the option
        self.config = (config or Config()).resolve()
        self.trajectory: dict[int, tuple[float, np.ndarray]] = {}  # source index -> (timestamp, T_world_cam)
        self.skipped: list[str] = []
        self.decode_s = 0.0
        self.start = 0  # first source position to stream (after a resume)
        self.released = 0  # source frames the stream has released (dropped and unreadable ones included)
        self.outputs = Outputs()  # a file that cannot be written (full disk) loses nothing, stops no mapping
        self.checkpoints = PeriodicCheckpoints(self.out / "checkpoint.pt", self.opts.checkpoint_every)

    def run(self) -> dict:
        from .folder_guard import check_folder, clear_stale

        with RunLock(self.out, force=self.opts.force_unlock):  # one run per results folder
            earlier = check_folder(self.out, self.opts.resume, self.opts.overwrite)  # never two runs' results mixed
            metrics = self._run()
            clear_stale(earlier)  # what the earlier run wrote and this one did not
            return metrics

    def _run(self) -> dict:
        self.open()  # the sequence, the held-out split, the pose source, the evaluator
        self.build()  # the Reconstructor: fresh, or restored from OUT/checkpoint.pt
        self.stream()  # the clock releases the source frames to the mapper
        self.drain()  # bounded drain (ME), or the offline reference's schedule; then +N PM
        self.evaluate()  # the final held-out metrics of the evaluated map state
        return self.write()  # map.ply, trajectory.txt, config.json, run.json, metrics.json, plots

    # ---- open ----------------------------------------------------------------------------------------------
    def open(self) -> None:
        from ..datasets import open_sequence
        from ..eval import HeldoutEvaluator
        from ..eval.tracked_heldout import track_heldout
        from .frame_faults import read_heldout

        from ..datasets.image_header import set_max_image_side

        self.out.mkdir(parents=True, exist_ok=True)
        set_max_image_side(self.config.max_image_side)  # image headers are checked against it before decoding
        seq = self.seq = open_sequence(self.path, **(self.opts.sequence_options or {}))
        self.n = len(seq) if self.opts.max_frames is None else min(len(seq), int(self.opts.max_frames))
        if self.n == 0:
            raise ValueError(f"{self.path}: the sequence has no frames")
        if self.config.clock.mode in ("cost", "realtime") and not self.opts.offline_reference:
            span = float(seq.timestamps[self.n - 1] - seq.timestamps[0]) + seq.frame_period_s
            check_speed_for(self.config.clock.speed, span, self.path)  # the floor: a run that ends
        self.held = heldout_indices(self.n, self.opts.holdout_every, self.opts.holdout_list)
        held_set = set(self.held)
        self.source = [i for i in range(self.n) if i not in held_set]
        self._position = {i: k for k, i in enumerate(self.source)}  # sequence index -> position in the stream
        self._next_progress = self.opts.eval_every_progress
        if not self.source:
            raise ValueError(f"{self.path}: every frame is held out; nothing left to map")
        self.config = self.config.resolve(depth_scale=float(seq.depth_scale))
        self.skipped = list(getattr(seq, "skipped_frames", ()))  # frames the reader left out (e.g. invalid poses)
        self.pose_name = pose_source_name(self.opts.pose, seq)  # what metrics.json names
        self.pose_source = prepare_pose_source(self.opts.pose, seq, self.source)
        if not self.held:
            log.warning("%s: no held-out frame (%d frames, --holdout-every %d): mapping all of them; there is no "
                        "held-out figure", self.path, self.n, self.opts.holdout_every)
        log.info("loading %d held-out views", len(self.held))
        self.heldout_frames, self.heldout_skipped = read_heldout(seq, self.held, self.config.depth_max,
                                                                 self.config.clock.on_bad_frame)  # unreadable: dropped
        self.heldout_tracking = track_heldout(self)  # no poses: held-out views posed by the run's pose source
        self.evaluator = HeldoutEvaluator(self.heldout_frames, sample_stride=self.opts.eval_sample_stride,
                                          checkpoint_ssim=self.opts.eval_ssim_at_checkpoints)

    # ---- build ---------------------------------------------------------------------------------------------
    def build(self) -> None:
        from ..budget import get_clock
        from ..mapper import Reconstructor

        ck_path = self.out / "checkpoint.pt"
        if self.opts.resume and ck_path.is_file():
            self.rec = self._resume(ck_path)
        else:  # the offline reference's policies are built with it (get_policies(cfg, offline=True))
            offline = len(self.source) if self.opts.offline_reference else None
            self.rec = Reconstructor(self.seq.camera, self.config.device, self.config, pose_source=self.pose_source,
                                     offline_frames=offline)
        self.config = self.rec.config
        self.cost_model_source = run_cost_model(self.rec, self.seq, self.source, self.path,
                                                offline=self.opts.offline_reference)
        self.clock = get_clock(self.config, offline=self.opts.offline_reference)
        self.rec.callbacks.append(self._maybe_checkpoint)
        if self.opts.view is not None:
            self.opts.view.attach(self.rec)  # a callback like evaluation's: its time is excluded from mapping

    def _resume(self, ck_path: Path):
        from ..io.checkpoint import read_checkpoint
        from ..mapper import Reconstructor

        ck = read_checkpoint(ck_path, sequence=self.seq)
        check_resume(self.out, ck, self.config, self._run_record())  # another config or split: refused
        if self.opts.offline_reference:  # a checkpoint of the first release does not record it
            ck.setdefault("offline_frames", len(self.source))
        rec = Reconstructor.from_checkpoint(ck, self.config.device, pose_source=self.pose_source)
        apply_new_settings(rec.config, self.config)
        extra = ck.get("extra") or {}
        self.start = int(extra.get("next_source", 0))
        self.released = self.start
        step = self.opts.eval_every_progress
        if step > 0:
            self._next_progress = (math.floor(self.released / len(self.source) / step + 1e-9) + 1) * step
        self.trajectory = {int(i): (float(ts), np.asarray(T, dtype=np.float64).reshape(4, 4))
                           for i, ts, T in extra.get("trajectory", [])}
        self.skipped = list(extra.get("skipped", []))
        self.evaluator.curve = list(extra.get("curve", []))
        log.info("resuming %s at source frame %d of %d", ck_path, self.start, len(self.source))
        for i in self.source[:self.start]:  # eligibility depends on the released source views, not on the mapper
            if i in self.trajectory:
                self.evaluator.observe_source(self.seq.frame(i, T_world_cam=self.trajectory[i][1],
                                                             depth_max=rec.config.depth_max))
        return rec

    # ---- stream --------------------------------------------------------------------------------------------
    def stream(self) -> None:
        self.rec.warmup()  # the renderer's one-time start-up cost is not paid by the stream's first frames
        self.wall0 = time.perf_counter()
        self.report = self.clock.run(self.rec, self._frames(), on_release=self._on_release)

    def _frames(self) -> Iterator[Frame]:
        rec, seq = self.rec, self.seq
        for k in _progress(range(self.start, len(self.source)), self.opts.progress, "mapping", len(self.source),
                           self.start):
            if self.opts.checkpoint_every and k > self.start and k % self.opts.checkpoint_every == 0:
                self._save_state(k)  # every frame before k has been integrated by now
            i = self.source[k]
            try:
                t0 = time.perf_counter()
                try:
                    frame = seq.frame(i, depth_max=self.config.depth_max)
                finally:  # decoding the recording is the sensor's work, not the mapper's (a live camera delivers
                    dt = time.perf_counter() - t0  # decoded images): off the mapper's clock
                    self.decode_s += dt
                    rec.stats.excluded_s += dt
                if self.pose_source is not None:
                    frame.T_world_cam = rec.track(frame, gt_pose=None if seq.poses is None else seq.poses[i])
            except BAD_FRAME_ERRORS as e:  # skipped and reported, or the run stops (clock.on_bad_frame)
                self.skipped.append(frame_fault(i, e, self.config.clock.on_bad_frame))
                continue
            self.trajectory[i] = (frame.timestamp, frame.T_world_cam)
            yield frame

    def _on_release(self, frame: Frame) -> None:
        t0 = time.perf_counter()
        # acquisition progress is the stream's (the paper's p = N_released / N_total): frames the mapper will drop
        # and unreadable frames before this one count, so a variant that falls behind is not squeezed into the start
        self.released = max(self.released, self._position.get(frame.index, self.released) + 1)
        self.evaluator.observe_source(frame)  # evaluation bookkeeping (cell eligibility): not mapping time
        if self.opts.view is not None:
            self.opts.view.observe(frame)
        step = self.opts.eval_every_progress
        if self.opts.eval_every and step > 0 and self.released / len(self.source) >= self._next_progress - 1e-9:
            self._next_progress += step * max(1, math.floor((self.released / len(self.source) -
                                                             self._next_progress) / step + 1e-9) + 1)
            if len(self.rec.gmap):
                self._checkpoint(self.rec)
        self.rec.stats.excluded_s += time.perf_counter() - t0

    def _render(self, frame: Frame):  # a held-out view at its pose (moved into a tracked map's frame by evaluate)
        return self.rec.render(frame.T_world_cam, frame.camera)

    def _checkpoint(self, r) -> None:
        self.evaluator.checkpoint(self._render, t_s=r.stats.mapping_s,
                                  progress=self.released / len(self.source), updates=r.stats.updates,
                                  supervised_mpix=r.stats.supervised_mpix, gaussians=len(r.gmap))

    def _maybe_checkpoint(self, r) -> None:
        if self.opts.eval_every and r.stats.updates % self.opts.eval_every == 0:
            self._checkpoint(r)

    def _save_state(self, next_source: int) -> None:
        t0 = time.perf_counter()
        extra = {"next_source": next_source, "skipped": self.skipped, "curve": self.evaluator.curve,
                 "trajectory": [[i, ts, T.reshape(-1).tolist()] for i, (ts, T) in sorted(self.trajectory.items())],
                 "run": self._run_record()}
        self.checkpoints.save(lambda: self.rec.save(self.out / "checkpoint.pt", extra=extra, sequence=self.seq),
                              next_source)  # a failed write warns and mapping goes on (retried next interval)
        self.rec.stats.excluded_s += time.perf_counter() - t0  # checkpoint I/O is not mapping time

    def _run_record(self) -> dict:  # the settings a resume must share (held-out split, pose source)
        return run_record(self.held, self.pose_name, self.opts.offline_reference)

    # ---- drain ---------------------------------------------------------------------------------------------
    def drain(self) -> None:
        from ..budget import offline_updates

        rec, opts = self.rec, self.opts
        if opts.offline_reference:
            rec.optimize(offline_updates(self.config.clock, len(self.source)))
            self.map_state = "offline-reference"
        else:
            drained = self.clock.drain(rec, self.seq_acquisition_s())
            self.report.drain_s = float(drained or 0.0)  # modelled seconds (cost clock); the others return None
            self.map_state = "ME"
        if opts.refine:
            rec.refine(opts.refine)
            self.map_state = f"+{opts.refine} PM" if not opts.offline_reference else \
                self.map_state + f" +{opts.refine} PM"
        self.wall_s = time.perf_counter() - self.wall0 - rec.stats.excluded_s
        rec.callbacks.remove(self._maybe_checkpoint)

    def seq_acquisition_s(self) -> float:
        from .results import acquisition_time

        return acquisition_time(self.seq, self.n)

    # ---- evaluate ------------------------------------------------------------------------------------------
    def evaluate(self) -> None:
        self.released = len(self.source)  # the stream has ended: every source frame was released
        self._checkpoint(self.rec)  # the curve ends at the evaluated map state (p = 1)
        self.trajectory = loop_closed(self.seq, self.trajectory, self.rec.loops)  # the final loop-closed poses
        self.accuracy = trajectory_accuracy_of(self.seq, self.trajectory, self.out, self.opts, self.outputs) \
            if self.pose_source is not None else {}
        if self.accuracy or self.heldout_tracking is not None:  # held-out poses into the tracked map's frame
            from ..eval.tracked_heldout import heldout_into_map_frame

            # evaluation poses stay the ground truth's (or the evaluation trajectory's), moved by the alignment of
            # the tracked source poses to them (the paper's "training-pose alignment")
            truth = dict(enumerate(self.seq.poses)) if self.accuracy else self.heldout_tracking.source_poses
            heldout_into_map_frame(self.heldout_frames, {i: T for i, (_, T) in self.trajectory.items()}, truth)
        self.final = self.evaluator.final(self._render)

    # ---- write ---------------------------------------------------------------------------------------------
    def write(self) -> dict:
        from .results import RunResult, collect_metrics, write_results

        tracking, views = self.heldout_tracking, self.rec.views
        result = RunResult(
            out=self.out, sequence=self.path, opts=self.opts, rec=self.rec, report=self.report, clock=self.clock.name,
            frames_total=self.n, frames_heldout=len(self.held), frames_source=len(self.source),
            map_state=self.map_state, pose_name=self.pose_name, tracked=self.pose_source is not None,
            cost_model_source=self.cost_model_source, final=self.final, accuracy=self.accuracy,
            heldout_untracked=None if tracking is None else tracking.untracked,
            curve=self.evaluator.curve, wall_s=self.wall_s, eval_s=self.evaluator.eval_seconds,
            decode_s=self.decode_s, acquisition_s=self.seq_acquisition_s(), skipped=self.skipped,
            heldout_skipped=self.heldout_skipped, trajectory=self.trajectory, heldout_frames=self.heldout_frames,
            render_heldout=self._render, outputs=self.outputs, checkpoint_failures=self.checkpoints.failures,
            fidelity_trace=getattr(self.rec.fidelity, "trace", None),  # the plain policies keep no trace
            views_trace=views.trace_rows() if hasattr(views, "trace_rows") else None)
        metrics = collect_metrics(result)
        write_results(result, metrics)
        return metrics


def _progress(items, enabled: bool, desc: str, total: int | None = None, initial: int = 0):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="frame", dynamic_ncols=True, total=total, initial=initial)
