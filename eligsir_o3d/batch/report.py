"""What a batch shows: one progress line per sequence (redrawn in place on a terminal, event lines otherwise),
and at the end ``summary.csv`` plus the side-by-side table of ``eligsir eval`` over the finished sequences."""

from __future__ import annotations

import csv
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable


@dataclass
class SequenceResult:
    """One sequence's outcome. status: done (mapped by this call), done-earlier (found finished), failed."""

    name: str
    path: str
    folder: str
    status: str
    error: str | None = None
    metrics: dict | None = None
    attempts: int = 0
    resumed_from: int | None = None


@dataclass
class _Line:
    state: str = "queued"
    frames: int = 0
    total: int | None = None
    attempt: int = 0
    t0: float | None = None
    f0: int = 0
    quarter: int = 0
    note: str = ""


@dataclass
class Progress:
    """Turns task events into terminal output: ``echo`` receives whole lines; ``live`` redraws a block."""

    names: list[str]
    echo: Callable[[str], None] = print
    live: bool = False
    lines: dict = field(default_factory=dict)
    _drawn: int = 0

    def __post_init__(self):
        self.lines = {n: _Line() for n in self.names}
        self.width = max((len(n) for n in self.names), default=4)

    def event(self, name: str, text: str) -> None:
        self._erase()
        self.echo(f"{name}: {text}")
        self._draw()

    def handle(self, name: str, info: dict) -> None:
        ln = self.lines.setdefault(name, _Line())
        ev = info.get("event")
        if ev in ("start", "resume"):
            ln.state, ln.attempt, ln.t0 = "mapping", info.get("attempt", 1), info.get("t", time.time())
            ln.frames = ln.f0 = info.get("resumed_from") or 0
            where = f" on {info['host']} (pid {info['pid']}, {info['threads']} thread(s))" if "pid" in info else ""
            if ev == "resume":
                self.event(name, f"attempt {ln.attempt} resumes from its checkpoint at source frame "
                                 f"{info['resumed_from']}{where}")
            else:
                self.event(name, f"attempt {ln.attempt} maps from frame 0{where}")
        elif ev == "progress":
            ln.frames, ln.total = info["frames"], info.get("total")
            if not self.live and ln.total:
                q = min(4, 4 * ln.frames // max(ln.total, 1))
                if 0 < q < 4 and q > ln.quarter:
                    ln.quarter = q
                    self.event(name, self.describe(name))
                    return
            self._erase()
            self._draw()
        elif ev == "done":
            ln.state = "done"
            psnr = info.get("psnr")
            self.event(name, f"done: held-out PSNR {psnr:.2f} dB, {info.get('updates')} updates"
                       if psnr is not None else "done")
        elif ev == "failed":
            ln.state = "failed"
            self.event(name, f"FAILED: {info.get('error')}")

    def describe(self, name: str) -> str:
        ln = self.lines[name]
        if ln.state != "mapping" or not ln.total:
            return ln.state
        pct = 100.0 * ln.frames / ln.total
        eta = "?"
        if ln.t0 is not None and ln.frames > ln.f0:
            rate = (time.time() - ln.t0) / (ln.frames - ln.f0)
            eta = _duration(rate * (ln.total - ln.frames))
        return f"{ln.frames}/{ln.total} frames ({pct:.0f}%), ETA {eta}, attempt {ln.attempt}"

    def _draw(self) -> None:
        if not self.live:
            return
        rows = [f"  {n.ljust(self.width)}  {self.describe(n)}" for n in self.names]
        sys.stdout.write("\n".join(rows) + "\n")
        sys.stdout.flush()
        self._drawn = len(rows)

    def _erase(self) -> None:
        if self.live and self._drawn:
            sys.stdout.write(f"\x1b[{self._drawn}F\x1b[J")  # up to the block's first line, clear below
            self._drawn = 0


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


SUMMARY_COLUMNS = ["name", "status", "psnr_db", "ssim", "depth_rmse_m", "cvq_auc_db", "cuc20", "mapping_time_s",
                   "wall_time_s", "peak_rss_mb", "updates", "gaussians", "frames_source", "attempts", "resumed_from",
                   "path", "folder", "error"]


def write_summary(results: list[SequenceResult], out: Path) -> Path:
    """``out/summary.csv``: a row per sequence (failed ones with their one-line error)."""
    import io

    from ..io.atomic import atomic_write_text

    path = Path(out) / "summary.csv"
    f = io.StringIO(newline="")  # written whole, then atomically: a failure names summary.csv, keeps the old one
    w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
    w.writeheader()
    for r in results:
        m = r.metrics or {}
        h = m.get("heldout") or {}
        w.writerow({"name": r.name, "status": r.status, "psnr_db": h.get("psnr"), "ssim": h.get("ssim"),
                    "depth_rmse_m": h.get("depth_rmse_m"), "cvq_auc_db": m.get("cvq_auc"),
                    "cuc20": m.get("cuc20_final"), "mapping_time_s": m.get("mapping_time_s"),
                    "wall_time_s": m.get("wall_time_s"), "peak_rss_mb": m.get("peak_rss_mb"),
                    "updates": m.get("updates"), "gaussians": m.get("gaussians"),
                    "frames_source": m.get("frames_source"), "attempts": r.attempts,
                    "resumed_from": r.resumed_from, "path": r.path, "folder": r.folder, "error": r.error})
    atomic_write_text(path, f.getvalue())
    return path


def comparison(results: list[SequenceResult]) -> str | None:
    """The ``eligsir eval`` table over the finished sequences (None when none finished)."""
    from ..eval import compare_results

    done = [Path(r.folder) for r in results if r.status != "failed"]
    return compare_results(done) if done else None
