"""Soak test: does memory stay within the configured caps, and per-frame latency flat, over a long stream?

    python benchmarks/budget/soak.py synthetic --frames 20000 --report-every 1000 --resolution 96x72
    python benchmarks/budget/soak.py synthetic                          # quick: 2,000 frames at 64x48
    python benchmarks/budget/soak.py kitchen --frames 1000 --sample-every 50     # eligsir map ... --realtime

``synthetic``: a stream of ``--frames`` frames through ``Reconstructor.integrate`` (``--updates`` updates each),
ray-cast from the embedded synthetic room along an orbit that circles the room every ``--loop`` frames, with the
radius, height and gaze drifting from loop to loop, so the camera keeps revisiting space with new poses: the map
saturates its Gaussian cap and the view policy keeps admitting and evicting views. Every frame has its own image
memory, as a live camera's would. The fidelity policy prices updates with the shipped cost model
(``rec.set_load(0, period, CostModel())``), so its decisions, and hence the run, do not depend on the machine's load.

Every ``--report-every`` frames it prints one row: peak RSS since the stream started (the high-water mark is reset
after the warm-up) and current RSS, what the map and the retained views hold,
the sizes of everything else that could grow with the stream (evidence voxels, microcells, the fidelity trace),
updates/s and mean integrate latency over the window (wall clock: noisy on a shared machine; RSS is not).

The bound it checks (exit status 1 when one fails):
- memory: peak RSS <= fixed + caps + slack. ``fixed`` = RSS at the end of the first window minus what the map and
  views held then (the interpreter, torch, Open3D, the scene, policy state); ``caps`` = what the configured caps
  allow: ``max_gaussians`` x 4 copies (parameter, gradient, two Adam moments) of each Gaussian's floats, doubled
  for an update's transient per-Gaussian tensors (activated values, projections, their gradients), plus
  ``max_views`` x 16 bytes per source pixel (float colour and depth) x 4/3 (cached resampled copies);
  ``slack`` = ``--slack-mb`` (allocator fragmentation, transient render buffers).
- no growth once saturated: from the first window in which the map is at its caps (Gaussians >= 95 % of the cap,
  retained views at their bound) to the end, RSS grows by at most ``--growth-mb``;
- latency: the last window's mean integrate CPU time per frame (``time.process_time``, all of this process's
  threads: on a shared machine the wall clock also counts other processes, the CPU time hardly does) is at most
  ``--latency-tolerance`` x that of the reference window (the saturation window, else the first), times the growth
  of the map between them (when it grew). Wall-clock latency and updates/s are printed beside it.

``kitchen``: the 1,000-frame real-time replay of ``../shared/data/7scenes_redkitchen_jpg1000`` through the same
pipeline as ``eligsir map SEQ --realtime --eval-every 0`` (no pictures or plots unless ``--pictures``; held-out
checkpoints only with ``--eval-every N``: the replay's clock stops while they render), with the RSS sampled every
``--sample-every`` released frames through the pipeline's per-frame hook (``RunOptions.view``, the live viewer's);
peak RSS, dropped frames and updates at the end, and the same memory bound with ``fixed`` = RSS when the stream
starts (held-out frames and evaluator loaded, renderer warm).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: spinning OpenMP threads starve a shared machine

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

import eligsir_o3d as eo3d  # noqa: E402
from eligsir_o3d.budget import CostModel  # noqa: E402
from eligsir_o3d.core.camera import look_at  # noqa: E402
from eligsir_o3d.datasets.synthetic import SyntheticRoom  # noqa: E402
from eligsir_o3d.core.frame import Frame  # noqa: E402
from eligsir_o3d.budget.memory import (cap_allowance_mb, current_rss_mb, map_memory_mb, peak_rss_mb,  # noqa: E402
                                       reset_peak_rss, retained_views_bound, structure_sizes, views_memory_mb)

KITCHEN = "../shared/data/7scenes_redkitchen_jpg1000"


# ---- the stream --------------------------------------------------------------------------------------------------
def orbit_pose(i: int, loop: int) -> np.ndarray:
    """Camera-to-world pose of frame ``i``: one circle of the room every ``loop`` frames, looking inward; radius,
    height and gaze drift slowly (periods of 3.7 and 5.3 loops), so revisits never repeat a pose exactly."""
    a = 2 * np.pi * i / loop
    slow, slower = 2 * np.pi * i / (3.7 * loop), 2 * np.pi * i / (5.3 * loop)
    r = 1.0 - 0.18 * (0.5 + 0.5 * np.sin(slow))
    eye = np.array([1.7 * r * np.cos(a), 1.3 * r * np.sin(a), 1.35 + 0.2 * np.sin(2 * a + slower)])
    side = np.array([-np.sin(a), np.cos(a), 0.0])
    target = np.array([0.0, 0.0, 0.75 + 0.15 * np.sin(3 * a)]) + 0.9 * np.sin(3 * a + 0.5 + slow) * side
    return look_at(eye, target)


def synthetic_frames(n: int, width: int, height: int, loop: int, fps: float = 30.0):
    """(room, iterator of n Frames): each one ray-cast anew (its own image memory), timestamps i / fps."""
    room = SyntheticRoom(n_frames=1, width=width, height=height)

    def frames():
        for i in range(n):
            T = orbit_pose(i, loop)
            color, depth = room.render(T)
            yield Frame.from_arrays(color, depth, room.camera, T, depth_scale=1.0, timestamp=i / fps, index=i)

    return room, frames()


# ---- what the caps allow (eligsir_o3d.budget.memory.cap_allowance_mb) -----------------------------------------------------------------------------------------
def caps_line(cfg) -> str:
    return (f"caps: max_gaussians={cfg.max_gaussians} views.max_views={retained_views_bound(cfg)} "
            f"views.active_size={cfg.views.active_size} growth.max_seeds_per_frame={cfg.growth.max_seeds_per_frame} "
            f"growth.max_insert_per_frame={cfg.growth.max_insert_per_frame} "
            f"fidelity.trace_max={getattr(cfg.fidelity, 'trace_max', None)} "
            f"evidence voxel {cfg.growth.voxel_size} m, microcell {cfg.views.cells.cell_size} m (bounded by the "
            f"scene's extent, not by a count)")


# ---- the synthetic soak ------------------------------------------------------------------------------------------
def soak(frames: int = 2000, report_every: int = 1000, resolution: tuple[int, int] = (64, 48), updates: int = 2,
         max_gaussians: int = 20_000, max_views_: int = 48, loop: int = 240, slack_mb: float = 64.0,
         growth_mb: float = 32.0, latency_tolerance: float = 2.0, config: eo3d.Config | None = None,
         out=print) -> dict:
    """Run the synthetic soak; returns {"rows", "caps", "budget_mb", "checks", "ok"} (see the module docstring)."""
    width, height = resolution
    cfg = config if config is not None else eo3d.Config()
    cfg.max_gaussians = int(max_gaussians)
    cfg.views.max_views = cfg.keyframes.max_views = int(max_views_)
    cfg.depth_scale = 1.0
    room, stream = synthetic_frames(frames, width, height, loop)
    rec = eo3d.Reconstructor(room.intrinsic, "cpu", cfg)
    rec.set_load(0, 1.0 / 30.0, CostModel())  # deterministic fidelity decisions (modelled update cost)
    rec.warmup()
    caps = cap_allowance_mb(rec.config, width, height)
    out(f"soak: {frames} frames of {width}x{height}, {updates} updates each, orbit of {loop} frames")
    out(caps_line(rec.config))
    out(f"cap allowance: Gaussians {caps['gaussians_mb']:.1f} MiB ({caps['bytes_per_gaussian']} B each), "
        f"views {caps['views_mb']:.1f} MiB")
    if not reset_peak_rss():
        out("note: the peak RSS could not be reset: it includes whatever this process did before the soak")
    rows, t_win, c_win, n_win, u0 = [], 0.0, 0.0, 0, 0
    for k, frame in enumerate(stream, 1):
        t0, c0 = time.perf_counter(), time.process_time()
        rec.integrate(frame, updates=updates)
        t_win += time.perf_counter() - t0
        c_win += time.process_time() - c0
        n_win += 1
        if k % report_every == 0 or k == frames:
            done = rec.stats.updates - u0
            row = {"frames": k, "peak_rss_mb": peak_rss_mb(), "rss_mb": current_rss_mb(),
                   "map_mb": map_memory_mb(rec.gmap), "views_mb": views_memory_mb(rec.views.views),
                   **structure_sizes(rec), "updates": rec.stats.updates,
                   "updates_per_s": done / t_win if t_win > 0 else None,
                   "latency_ms": 1000.0 * t_win / max(1, n_win), "cpu_ms": 1000.0 * c_win / max(1, n_win)}
            rows.append(row)
            out(_row_text(row))
            t_win, c_win, n_win, u0 = 0.0, 0.0, 0, rec.stats.updates
    result = verdict(rows, caps, slack_mb, growth_mb, latency_tolerance)
    for line in result["lines"]:
        out(line)
    result.update(rows=rows, caps=caps, config=rec.config.to_dict())
    return result


def _row_text(r: dict) -> str:
    ups = "-" if r["updates_per_s"] is None else f"{r['updates_per_s']:.1f}"
    return (f"frames {r['frames']:>6}  peak RSS {r['peak_rss_mb']:7.1f} MiB  RSS {r['rss_mb']:7.1f}  "
            f"map {r['map_mb']:6.1f}  views {r['views_mb']:6.1f}  | Gaussians {r['gaussians']:>7}  "
            f"views {r['views']:>4}  evidence voxels {r['evidence_voxels']}  microcells {r['microcells']}  "
            f"fidelity trace {r['fidelity_trace']}  | updates/s {ups}  latency {r['latency_ms']:.1f} ms/frame "
            f"(CPU {r['cpu_ms']:.1f} ms)")


def verdict(rows: list[dict], caps: dict, slack_mb: float, growth_mb: float, tolerance: float) -> dict:
    """The three checks of the module docstring over the report rows."""
    first = rows[0]
    fixed = first["rss_mb"] - first["map_mb"] - first["views_mb"]
    budget = fixed + caps["gaussians_mb"] + caps["views_mb"] + slack_mb
    peak = max(r["peak_rss_mb"] for r in rows)
    sat = next((i for i, r in enumerate(rows) if r["gaussians"] >= 0.95 * caps["max_gaussians"]
                and r["views"] >= caps["max_views"]), None)
    ref = rows[sat] if sat is not None else first
    last = rows[-1]
    checks = {"memory": {"ok": peak <= budget, "peak_rss_mb": peak, "budget_mb": budget, "fixed_mb": fixed}}
    if sat is not None and sat < len(rows) - 1:
        grew = last["rss_mb"] - ref["rss_mb"]
        checks["growth"] = {"ok": grew <= growth_mb, "saturated_at_frame": ref["frames"], "rss_growth_mb": grew,
                            "limit_mb": growth_mb}
    if len(rows) > 1 and ref is not last:
        explained = max(1.0, last["gaussians"] / max(1, ref["gaussians"]))
        ratio = last["cpu_ms"] / ref["cpu_ms"] if ref["cpu_ms"] > 0 else float("inf")
        wall = last["latency_ms"] / ref["latency_ms"] if ref["latency_ms"] > 0 else float("inf")
        checks["latency"] = {"ok": ratio <= tolerance * explained, "ratio": ratio, "wall_ratio": wall,
                             "explained_by_map": explained, "reference_frame": ref["frames"], "tolerance": tolerance}
    ok = all(c["ok"] for c in checks.values())
    lines = [f"memory: peak RSS {peak:.1f} MiB vs budget {budget:.1f} MiB = fixed {fixed:.1f} + Gaussian cap "
             f"{caps['gaussians_mb']:.1f} + view cap {caps['views_mb']:.1f} + slack {slack_mb:.0f}: "
             f"{'ok' if checks['memory']['ok'] else 'EXCEEDED'}"]
    if "growth" in checks:
        g = checks["growth"]
        lines.append(f"growth after saturation (frame {g['saturated_at_frame']}): RSS {g['rss_growth_mb']:+.1f} MiB "
                     f"(limit {growth_mb:.0f}): {'ok' if g['ok'] else 'GROWING'}")
    else:
        lines.append("growth after saturation: not checked (the map did not reach its caps before the last report)")
    if "latency" in checks:
        c = checks["latency"]
        lines.append(f"latency (CPU time per frame): last window / window to frame {c['reference_frame']} = "
                     f"{c['ratio']:.2f} (wall {c['wall_ratio']:.2f}; map growth explains {c['explained_by_map']:.2f}x, "
                     f"tolerance {tolerance:g}x): {'ok' if c['ok'] else 'GROWING'}")
    lines.append("soak: OK" if ok else "soak: FAILED")
    return {"checks": checks, "ok": ok, "budget_mb": budget, "lines": lines}


# ---- the kitchen real-time replay --------------------------------------------------------------------------------
class RSSSampler:
    """The pipeline's per-frame hook (``RunOptions.view``): the RSS every ``every`` released frames."""

    def __init__(self, every: int = 50, out=print):
        self.every, self.out = max(1, int(every)), out
        self.released, self.samples, self.rec, self.start_rss_mb, self.start_peak_mb = 0, [], None, None, None
        self.mapping_peak_mb = None  # peak RSS at the last update (stream and drain; final evaluation excluded)

    def attach(self, rec) -> None:
        self.rec = rec
        rec.callbacks.append(self._after_update)  # after every update, its time excluded like evaluation's

    def _after_update(self, rec) -> None:
        self.mapping_peak_mb = peak_rss_mb()

    def observe(self, frame) -> None:
        if self.start_rss_mb is None:  # the stream's first release: held-out views loaded, renderer warm
            self.start_rss_mb, self.start_peak_mb = current_rss_mb(), peak_rss_mb()
        self.released += 1
        if self.released % self.every == 0:
            s = {"released": self.released, "rss_mb": current_rss_mb(), "peak_rss_mb": peak_rss_mb(),
                 "updates": self.rec.stats.updates, **structure_sizes(self.rec)}
            self.samples.append(s)
            self.out(f"released {s['released']:>5}  peak RSS {s['peak_rss_mb']:7.1f} MiB  RSS {s['rss_mb']:7.1f}  "
                     f"Gaussians {s['gaussians']:>7}  views {s['views']:>4}  updates {s['updates']}")


def kitchen(frames: int = 1000, sample_every: int = 50, path: str = KITCHEN, pictures: bool = False,
            slack_mb: float = 64.0, eval_every: int = 0, holdout_every: int = 8, out=print) -> dict:
    """The real-time replay of ``path`` (``eligsir map path --realtime --max-frames frames --eval-every N``), RSS
    sampled."""
    from eligsir_o3d.run.pipeline import MappingPipeline, RunOptions

    cfg = eo3d.Config()
    cfg.clock.mode = "realtime"
    sampler = RSSSampler(sample_every, out)
    opts = RunOptions(max_frames=frames, view=sampler, progress=False, plots=pictures, pictures=pictures,
                      eval_every=eval_every, holdout_every=holdout_every)
    out(caps_line(cfg))
    reset_peak_rss()  # this run's peak, also inside a longer process
    with tempfile.TemporaryDirectory(prefix="soak_kitchen_") as tmp:
        here = ROOT / path  # KITCHEN is relative to the repository root; "synthetic" and absolute paths pass through
        pipe = MappingPipeline(str(here) if here.exists() else path, tmp, cfg, opts)
        m = pipe.run()
    caps = cap_allowance_mb(pipe.rec.config, pipe.rec.camera.width, pipe.rec.camera.height)
    peak = max([peak_rss_mb()] + [s["peak_rss_mb"] for s in sampler.samples])
    budget = (sampler.start_rss_mb or 0.0) + caps["gaussians_mb"] + caps["views_mb"] + slack_mb
    res = {"frames": frames, "peak_rss_mb": peak, "start_rss_mb": sampler.start_rss_mb,
           "peak_before_stream_mb": sampler.start_peak_mb, "heldout_views": len(pipe.heldout_frames), "peak_mapping_mb": sampler.mapping_peak_mb,
           "budget_mb": budget,
           "dropped_frames": m["dropped_frames"], "frames_released": m["frames_released"], "updates": m["updates"],
           "gaussians": m["gaussians"], "retained_views": m["policies"]["views"].get("retained"),
           "heldout_psnr": m["heldout"]["psnr"], "samples": sampler.samples, "caps": caps,
           "ok": peak <= budget}
    out(f"kitchen: {m['frames_released']} frames released, {m['dropped_frames']} dropped, {m['updates']} updates, "
        f"{m['gaussians']} Gaussians, {res['retained_views']} retained views, held-out PSNR {res['heldout_psnr']:.2f}")
    out(f"before the stream (sequence opened, {res['heldout_views']} held-out views loaded, renderer warm): RSS {sampler.start_rss_mb:.1f} "
        f"MiB, peak {sampler.start_peak_mb:.1f} MiB; peak at the last update (stream and drain) "
        f"{sampler.mapping_peak_mb:.1f} MiB; at the end (final evaluation and writing included) {peak:.1f} MiB")
    out(f"memory: peak RSS {peak:.1f} MiB vs budget {budget:.1f} MiB = RSS at stream start "
        f"{sampler.start_rss_mb:.1f} + Gaussian cap {caps['gaussians_mb']:.1f} + view cap {caps['views_mb']:.1f} "
        f"+ slack {slack_mb:.0f}: {'ok' if res['ok'] else 'EXCEEDED'}")
    return res


# ---- command line ------------------------------------------------------------------------------------------------
def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--resolution {text!r}: expected WxH, e.g. 64x48") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"--resolution {text!r}: at least 8x8")
    return w, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="mode")
    s = sub.add_parser("synthetic", help="a long synthetic stream through Reconstructor.integrate (default)")
    s.add_argument("--frames", type=int, default=2000)
    s.add_argument("--report-every", type=int, default=500)
    s.add_argument("--resolution", type=_resolution, default=(64, 48), help="WxH (default 64x48)")
    s.add_argument("--updates", type=int, default=2, help="updates per frame")
    s.add_argument("--max-gaussians", type=int, default=20_000)
    s.add_argument("--max-views", type=int, default=48)
    s.add_argument("--loop", type=int, default=240, help="frames per circle of the room")
    s.add_argument("--slack-mb", type=float, default=64.0)
    s.add_argument("--growth-mb", type=float, default=32.0)
    s.add_argument("--latency-tolerance", type=float, default=2.0)
    s.add_argument("--json", type=Path, help="also write the rows and checks here")
    k = sub.add_parser("kitchen", help="the real-time replay of the 7-Scenes kitchen (eligsir map --realtime)")
    k.add_argument("--frames", type=int, default=1000)
    k.add_argument("--sample-every", type=int, default=50)
    k.add_argument("--path", default=KITCHEN)
    k.add_argument("--pictures", action="store_true", help="also write pictures and plots (as eligsir map does)")
    k.add_argument("--slack-mb", type=float, default=64.0)
    k.add_argument("--eval-every", type=int, default=0, help="held-out checkpoints every N updates (default 0: only "
                   "the final evaluation; each checkpoint renders every held-out view, which the replay waits for)")
    k.add_argument("--holdout-every", type=int, default=8, help="held-out split period (default 8: 125 views of "
                   "1,000 frames; 40: 25 views), to compare the memory the evaluation split takes")
    k.add_argument("--json", type=Path)
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("synthetic", "kitchen", "-h", "--help"):
        argv = ["synthetic", *argv]  # the synthetic soak is the default mode
    args = ap.parse_args(argv)
    if args.mode == "kitchen":
        res = kitchen(args.frames, args.sample_every, args.path, args.pictures, args.slack_mb, args.eval_every,
                      args.holdout_every)
    else:
        if args.frames < 1 or args.report_every < 1:
            ap.error("--frames and --report-every must be at least 1")
        res = soak(args.frames, args.report_every, args.resolution, args.updates, args.max_gaussians,
                   args.max_views, args.loop, args.slack_mb, args.growth_mb, args.latency_tolerance)
        res.pop("lines", None)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=lambda x: None if isinstance(x, float)
                                        and not math.isfinite(x) else str(x)))
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
