"""Writing a results file so that a full disk or an I/O error never destroys what is already there.

Every file of a results folder (checkpoint.pt, map.ply, metrics.json, config.json, pictures, plots) is written to a
temporary file in the same folder, flushed and fsynced, then renamed over the previous version (``os.replace`` is
atomic on one filesystem): a write that fails half-way - ``ENOSPC``, ``EIO``, a quota, a killed process - leaves
the previous file intact and loadable, and the temporary file is removed.

Only a regular file (or a new path) is replaced. Any other target is never replaced (:func:`output_kind`): a
character device (``/dev/null``, ``/dev/full``) or a FIFO with a reader is written directly (``/dev/full`` then
fails with ``ENOSPC``, the node untouched); a directory, a FIFO without a reader, a block device or a socket is
refused. Writers that need a temporary file of their own (Open3D, video encoders) take it from :func:`temp_for` and
finish with :func:`commit_file`, which applies the same rule; their errors name the target, never the temporary.

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
import shutil
import stat
import tempfile
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


def output_kind(path: str | Path) -> str:
    """What ``path`` is as an output target (links followed): "new", "file", "device" (a character device),
    "fifo", "directory" or "other" (a block device, a socket)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "new"
    except OSError as e:
        raise WriteFailed(path, f"[Errno {e.errno}] {e.strerror}", e.errno) from None
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISCHR(mode):
        return "device"
    if stat.S_ISFIFO(mode):
        return "fifo"
    return "directory" if stat.S_ISDIR(mode) else "other"


def _open_direct(path: Path, kind: str) -> BinaryIO:
    """``path`` (a character device or a FIFO) opened for writing, never created or replaced."""
    if kind not in ("device", "fifo"):
        what = {"directory": "is a directory", "other": "is not a regular file (a block device or a socket)"}[kind]
        raise WriteFailed(path, f"{what}; give a file path", _errno.EISDIR if kind == "directory" else None)
    try:
        fd = os.open(path, os.O_WRONLY | (os.O_NONBLOCK if kind == "fifo" else 0))
    except OSError as e:
        if e.errno == _errno.ENXIO:
            raise WriteFailed(path, "a FIFO with no reader", e.errno) from None
        raise write_failed(path, e) from None
    if kind == "fifo":
        os.set_blocking(fd, True)
    return os.fdopen(fd, "wb")


def temp_for(path: str | Path, suffix: str | None = None) -> Path:
    """A temporary path for a writer that must name its output file: beside ``path`` (so the rename is atomic)
    when ``path`` is a regular file or new, else in the system's temporary folder. ``suffix``: the temporary's
    (the format's) suffix, default ``path``'s."""
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    if output_kind(path) in ("new", "file"):
        return path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    fd, name = tempfile.mkstemp(prefix="eligsir-", suffix=suffix)
    os.close(fd)
    return Path(name)


def commit_file(tmp: str | Path, path: str | Path) -> Path:
    """Put the finished temporary file ``tmp`` (from :func:`temp_for`) at ``path``: renamed over a regular file
    or a new path; copied into a character device or a FIFO with a reader; refused for anything else. ``tmp`` is
    removed in every case; a failure is :class:`WriteFailed` naming ``path``."""
    tmp, path = Path(tmp), Path(path)
    try:
        kind = output_kind(path)
        if kind in ("new", "file"):
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, path)
            _fsync_dir(path.parent)
        else:
            with _open_direct(path, kind) as out, open(tmp, "rb") as f:
                shutil.copyfileobj(f, out)
                out.flush()
    except OSError as e:
        raise write_failed(path, e) from None
    finally:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
    return path


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Write ``path`` through ``write(f)`` (``f`` an open binary file) atomically: temporary file in the same
    folder, flush, fsync, ``os.replace``. On any failure the temporary file is removed, ``path`` keeps its previous
    content, and OS errors (also wrapped in a library's RuntimeError) are raised as :class:`WriteFailed`
    (KeyboardInterrupt and other exceptions pass unchanged)."""
    path = Path(path)
    kind = output_kind(path)
    if kind not in ("new", "file"):  # a device or FIFO is written, never replaced; anything else refused
        try:
            with _open_direct(path, kind) as f:
                write(f)
                f.flush()
        except OSError as e:
            raise write_failed(path, e) from None
        return path
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
