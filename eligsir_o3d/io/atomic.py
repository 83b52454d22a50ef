"""Writing a results file so that a full disk or an I/O error never destroys what is already there.

Every file of a results folder (checkpoint.pt, map.ply, metrics.json, config.json, pictures, plots) is written to a
temporary file in the same folder, flushed and fsynced, then renamed over the previous version (``os.replace`` is
atomic on one filesystem): a write that fails half-way - ``ENOSPC``, ``EIO``, a quota, a killed process - leaves
the previous file intact and loadable, and the temporary file is removed.

A failed write raises :class:`WriteFailed`, an ``OSError`` whose one-line message names the file and the operating
system's reason (``cannot write runs/x/map.ply: [Errno 28] No space left on device``), also when the writer was a
library that wrapped the OSError in its own exception (``torch.save`` raises a RuntimeError whose context is the
OSError).

    atomic_write(path, lambda f: torch.save(payload, f))
    atomic_write_text(out / "metrics.json", json.dumps(metrics))
"""

from __future__ import annotations

import errno as _errno
import os
from pathlib import Path
from typing import BinaryIO, Callable

EXIT_WRITE_FAILED = 3  # eligsir map's exit status when a results file could not be written (README: exit codes)


class WriteFailed(OSError):
    """A results file that could not be written; ``str()`` is one line naming the file and the OS error."""

    exit_code = EXIT_WRITE_FAILED

    def __init__(self, path: str | Path, reason: str, errno: int | None = None):
        super().__init__(errno, reason)
        self.path, self.reason = Path(path), reason

    def __str__(self) -> str:
        return f"cannot write {self.path}: {self.reason}"

    def __reduce__(self):  # picklable (batch runs report across processes)
        return (type(self), (str(self.path), self.reason, self.errno))


def write_failed(path: str | Path, e: BaseException) -> WriteFailed:
    """The :class:`WriteFailed` for exception ``e`` raised while writing ``path``: the OSError found in ``e`` or
    its context chain gives the errno and reason; otherwise the exception's first line."""
    if isinstance(e, WriteFailed):
        return e
    os_err = _os_error(e)
    if os_err is not None:
        name = _errno.errorcode.get(os_err.errno, "")
        reason = f"[Errno {os_err.errno}{' ' + name if name else ''}] {os_err.strerror or os.strerror(os_err.errno)}"
        return WriteFailed(path, reason, os_err.errno)
    first = str(e).splitlines()[0] if str(e) else ""
    return WriteFailed(path, f"{type(e).__name__}: {first}" if first else type(e).__name__)


def _os_error(e: BaseException) -> OSError | None:
    """The OSError (with an errno) that is ``e`` or in its cause/context chain."""
    seen, cur = set(), e
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, OSError) and cur.errno is not None:
            return cur
        cur = cur.__cause__ or cur.__context__
    return None


def _fsync_dir(folder: Path) -> None:
    try:  # make the rename itself durable (not possible on every platform/filesystem)
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Write ``path`` through ``write(f)`` (``f`` an open binary file) atomically: temporary file in the same
    folder, flush, fsync, ``os.replace``. On any failure the temporary file is removed, ``path`` keeps its previous
    content, and OS errors (also wrapped in a library's RuntimeError) are raised as :class:`WriteFailed`
    (KeyboardInterrupt and other exceptions pass unchanged)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for stale in path.parent.glob(f".{path.name}.*.tmp"):  # left by a writer that was killed
            stale.unlink(missing_ok=True)
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if isinstance(e, OSError) or (isinstance(e, RuntimeError) and _os_error(e) is not None):
            raise write_failed(path, e) from e  # a library's wrapped I/O error too (torch.save: RuntimeError)
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """:func:`atomic_write` of a UTF-8 text."""
    data = text.encode("utf-8")
    return atomic_write(path, lambda f: f.write(data))
