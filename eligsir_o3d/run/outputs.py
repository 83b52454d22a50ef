"""What a run does when a results file cannot be written (full disk, I/O error, quota): nothing already on disk is
lost (every file is written atomically, :mod:`.atomic_io`), and the run says what failed in one line.

- Periodic checkpoints (``--checkpoint-every``): a failed write warns once, mapping continues, and the next interval
  tries again (and says when it works again); every failure is listed in metrics.json's ``checkpoint_failures``.
- Final outputs (map.ply, trajectory.txt, config.json, pictures, run.json, metrics.json, plots): each stage that
  fails is recorded and the later stages are still written (if the pictures fail, map.ply and metrics.json are
  there, metrics.json lists what failed in ``write_failures``); then :meth:`Outputs.finish` raises one
  :class:`~.atomic_io.WriteFailed` naming the first file that failed (``eligsir map`` exits with status 3).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

from ..io.atomic import WriteFailed, write_failed

log = logging.getLogger("eligsir_o3d")


class PeriodicCheckpoints:
    """Checkpoint writes during mapping that must never stop it: ``save`` returns whether the write worked."""

    def __init__(self, path: str | Path, every: int):
        self.path, self.every = Path(path), int(every)
        self.failures: list[dict] = []  # {"next_source": k, "error": one line}, for metrics.json
        self._failing = False

    def save(self, write: Callable[[], object], next_source: int) -> bool:
        try:
            write()
        except OSError as e:  # WriteFailed, or an OSError raised before the atomic write began
            err = write_failed(self.path, e)
            self.failures.append({"next_source": int(next_source), "error": str(err)})
            if len(self.failures) == 1:
                log.warning("%s; mapping continues, the previous checkpoint (if any) is unchanged, and the checkpoint "
                            "is tried again every %d source frames", err, self.every)
            else:
                log.info("checkpoint at source frame %d failed again (%s); trying again in %d frames",
                         next_source, err.reason, self.every)
            self._failing = True
            return False
        if self._failing:
            log.warning("checkpoint %s written again at source frame %d (after %d failed attempt(s))", self.path,
                        next_source, len(self.failures))
            self._failing = False
        return True


class Outputs:
    """Writes a results folder stage by stage; a stage that fails with an OSError is recorded, not fatal."""

    def __init__(self):
        self.failures: list[WriteFailed] = []
        self.skipped: list[str] = []  # optional outputs left out, one line each (metrics.json: outputs_skipped)

    def stage(self, path: str | Path, write: Callable, *args, **kwargs):
        """``write(*args, **kwargs)``; on an OSError: recorded (named ``path`` unless the error names its own
        file), logged, and None returned."""
        try:
            return write(*args, **kwargs)
        except OSError as e:
            err = write_failed(path, e)
            log.info("%s; writing the other results files", err)  # the one error line comes from finish()
            self.failures.append(err)
            return None

    def optional(self, path: str | Path, write: Callable, *args, **kwargs):
        """An output the user asked for besides the results (map.spz, map.splat): as :meth:`stage`, and a map
        this format cannot hold (a ValueError, e.g. beyond SPZ's reach) costs that file and a warning only
        (listed in :attr:`skipped`), never the run's other results."""
        try:
            return self.stage(path, write, *args, **kwargs)
        except ValueError as e:
            msg = f"{Path(path).name} not written: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
            log.warning("%s", msg)
            self.skipped.append(msg)
            return None

    def messages(self) -> list[str]:
        return [str(f) for f in self.failures]

    def finish(self, metrics: dict | None = None) -> None:
        """Raise one :class:`WriteFailed` (the first failure; the others named in the same line) if any stage
        failed. ``metrics``: handed to the caller as the exception's ``metrics``."""
        if not self.failures:
            return
        first, others = self.failures[0], [f.path.name for f in self.failures[1:]]
        reason = first.reason + (f" (also not written: {', '.join(others)})" if others else "")
        err = WriteFailed(first.path, reason, first.errno)
        err.metrics = metrics
        raise err
