"""The worker side of a batch: one call maps one sequence with the same entry point as ``eligsir map``
(:func:`eligsir_o3d.run.pipeline.run_mapping`), resuming from the folder's checkpoint when an earlier attempt died.

Runs inside a Ray worker (or any process): nothing here imports Ray. Progress goes to ``report(name, info)``,
a callable the driver hands in (a Ray actor's method on a cluster).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Callable

from .specs import folder_status, read_state, start_state, write_state

log = logging.getLogger("eligsir_o3d.batch")


def set_threads(cpus: float) -> int:
    """Match torch's and numba's thread pools to the task's CPU share, so tasks side by side do not oversubscribe.

    numba.set_num_threads (not the NUMBA_NUM_THREADS variable, which fixes the pool's size once per process and
    would cap a later, larger task in a reused worker) and torch.set_num_threads act per process, at once.
    """
    n = max(1, int(cpus))
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch's first import in this worker
    os.environ["OMP_NUM_THREADS"] = str(n)
    import torch

    torch.set_num_threads(n)
    try:
        import numba

        from ..runtime import jit  # noqa: F401  picks numba's threading layer (TBB where it loads) before its first use

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    except ImportError:  # numba is a dependency; without it the compiled CPU renderer is off anyway
        pass
    return n


def one_line(e: BaseException) -> str:
    text = str(e).strip()
    first = text.splitlines()[0] if text else ""
    if isinstance(e, (ValueError, OSError)) and first:
        return first
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


def map_sequence(request: dict, out_root: str, cpus: float = 1, device: str | None = None,
                 report: Callable[[str, dict], None] | None = None) -> dict:
    """Map ``request`` (see specs.build_request) into ``out_root/<name>``; never raises for a bad sequence.

    Returns {"name", "status": done | failed, "error", "metrics", "attempts", "resumed_from", "folder"}.
    """
    name = request["name"]
    folder = Path(out_root) / name

    def send(info: dict) -> None:
        if report is not None:
            try:
                report(name, info)
            except Exception as e:  # noqa: BLE001 - progress is best effort; the mapping goes on
                log.debug("progress message lost: %s", e)
    result = {"name": name, "path": request["path"], "folder": str(folder), "status": "failed", "error": None,
              "metrics": None, "attempts": 0, "resumed_from": None}
    try:
        status = folder_status(folder, request)
        if status == "foreign":
            raise ValueError(f"{folder}: exists and was not written by eligsir batch; choose another --out or "
                             f"remove it")
        if status == "done":  # finished meanwhile (a second driver, or a retry after the last write)
            import json

            result.update(status="done", metrics=json.loads((folder / "metrics.json").read_text()),
                          attempts=(read_state(folder) or {}).get("attempts", 1))
            return result
        if status == "changed":  # our own folder, mapped with other options: start over
            for f in ("checkpoint.pt", "metrics.json"):
                (folder / f).unlink(missing_ok=True)
        resume_from = _checkpoint_frame(folder) if status == "resume" else None
        state = start_state(folder, request)
        state["resumed_from"] = resume_from
        write_state(folder, state)
        result.update(attempts=state["attempts"], resumed_from=resume_from)
    except Exception as e:  # noqa: BLE001 - a task reports, the batch goes on
        result["error"] = one_line(e)
        send({"event": "failed", "error": result["error"]})
        return result

    threads = set_threads(cpus)
    send({"event": "resume" if resume_from is not None else "start", "attempt": state["attempts"],
          "resumed_from": resume_from, "pid": os.getpid(), "host": state["host"], "threads": threads})
    try:
        with _log_to(folder / "batch.log"), _frame_progress(send):
            metrics = _run(request, folder, device, resume_from is not None)
    except Exception as e:  # noqa: BLE001
        result["error"] = one_line(e)
        state.update(state="failed", error=result["error"])
        write_state(folder, state)
        send({"event": "failed", "error": result["error"]})
        return result
    state.update(state="done", finished=time.time())
    write_state(folder, state)
    result.update(status="done", metrics=metrics)
    send({"event": "done", "updates": metrics.get("updates"), "psnr": (metrics.get("heldout") or {}).get("psnr")})
    return result


def _run(request: dict, folder: Path, device: str | None, resume: bool) -> dict:
    from ..config import Config
    from ..run.pipeline import RunOptions, run_mapping

    cfg = Config.from_dict(request["config"])
    if device is not None:
        cfg.device = device
    # a retry resumes the folder of an attempt that died, maybe on another machine: its lock is taken over
    opts = RunOptions(**request["options"], resume=resume, force_unlock=resume, progress=True,
                      overwrite=True)  # the batch decided (folder_status) that this folder is its own to remap
    return run_mapping(request["path"], folder, cfg, opts)


def _checkpoint_frame(folder: Path) -> int | None:
    """The source frame the folder's checkpoint continues at (None: no usable checkpoint, start at frame 0)."""
    from ..io.checkpoint import CheckpointError, read_checkpoint

    ck = folder / "checkpoint.pt"
    if not ck.is_file():
        return None
    try:
        return int((read_checkpoint(ck).get("extra") or {}).get("next_source", 0))
    except (CheckpointError, TypeError, ValueError) as e:
        log.warning("%s; mapping from frame 0", e)
        shutil.move(str(ck), str(folder / "checkpoint.unreadable.pt"))
        return None


@contextlib.contextmanager
def _log_to(path: Path):
    """The package's log lines of this task (resume frame, skipped frames ...) go to the sequence's batch.log."""
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    pkg = logging.getLogger("eligsir_o3d")
    old_level = pkg.level
    pkg.addHandler(handler)
    pkg.setLevel(logging.INFO)
    try:
        yield
    finally:
        pkg.removeHandler(handler)
        pkg.setLevel(old_level)
        handler.close()


@contextlib.contextmanager
def _frame_progress(send: Callable[[dict], None], every_s: float = 1.0):
    """Frames done of the mapping loop, from its progress bar: run_mapping draws one with tqdm (desc 'mapping')
    when RunOptions.progress is on; here that bar draws nowhere and reports its count instead."""
    import tqdm as tqdm_pkg

    base = tqdm_pkg.tqdm
    sink = open(os.devnull, "w")  # noqa: SIM115 - closed below

    class Reporting(base):
        def __init__(self, *args, **kwargs):
            self._report = kwargs.get("desc") == "mapping"
            kwargs["file"] = sink
            super().__init__(*args, **kwargs)

        def __iter__(self):
            done, last = self.n, 0.0
            for item in super().__iter__():
                now = time.monotonic()
                if self._report and now - last >= every_s:
                    send({"event": "progress", "frames": done, "total": self.total})
                    last = now
                done += 1
                yield item
            if self._report:
                send({"event": "progress", "frames": done, "total": self.total})

    tqdm_pkg.tqdm = Reporting
    try:
        yield
    finally:
        tqdm_pkg.tqdm = base
        sink.close()
