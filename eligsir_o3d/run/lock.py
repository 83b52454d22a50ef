"""One run per results folder: ``OUT/eligsir.lock`` names the run that writes there (pid, host, start time,
command line), so a second ``eligsir map --out OUT`` refuses instead of interleaving its files with the first's.

- The lock is taken before anything is written and released on every way out of the run (normal end, error,
  KeyboardInterrupt); a SIGKILLed run leaves it behind.
- A lock left by a process that no longer runs on this host is stale: it is taken over with a warning.
- A lock from another host (a shared network folder) cannot be checked from here: it is respected unless the run
  is given ``force=True`` (``eligsir map --force-unlock``), which takes it over with a warning.

Taking the lock is atomic between processes of one host: the file is created with ``O_CREAT`` (``O_NOFOLLOW``:
a symbolic link in its place is refused, never written through; so is a hard link or anything not a plain file) and
its owner record written under an exclusive ``flock``, which the owner keeps for the whole run (the kernel drops it when the
owner dies, even by SIGKILL).
"""

from __future__ import annotations

import datetime
import errno
import json
import logging
import os
import socket
import sys
from pathlib import Path

log = logging.getLogger("eligsir_o3d")

LOCK_FILE = "eligsir.lock"
EXIT_LOCKED = 4  # eligsir map's exit status when the results folder is in use (README: exit codes)


class RunLocked(RuntimeError):
    """The results folder is held by another run (the message names it)."""

    exit_code = EXIT_LOCKED


def _host() -> str:
    return socket.gethostname()


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (a zombie counts as dead)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    try:  # Linux: a zombie (exited, not yet reaped) holds no lock
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def describe(owner: dict) -> str:
    """``pid 123 on host h, started YYYY-MM-DD hh:mm:ss UTC (eligsir map ... )``."""
    cmd = f" ({owner['command']})" if owner.get("command") else ""
    return f"pid {owner.get('pid', '?')} on host {owner.get('host', '?')}, started {owner.get('started', '?')}{cmd}"


class RunLock:
    """``with RunLock(out):`` holds ``out/eligsir.lock`` for the block; raises :class:`RunLocked` if another live
    run holds it. ``force``: take over a lock from another host too."""

    def __init__(self, folder: str | Path, force: bool = False):
        self.folder, self.force = Path(folder), bool(force)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def __enter__(self) -> "RunLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        import fcntl

        from ..io.atomic import write_failed

        try:  # a folder that cannot be created or written (read-only, permissions): a write failure, exit 3
            self.folder.mkdir(parents=True, exist_ok=True)
            if not os.access(self.folder, os.W_OK | os.X_OK):
                raise PermissionError(13, "Permission denied (the folder is not writable)")
        except OSError as e:
            raise write_failed(self.path, e) from None
        for _ in range(10):  # the file may be replaced between open and flock: then try the new one
            fd = self._open()
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # a live process of this host holds it right now
                os.close(fd)
                raise RunLocked(self._refusal(self._read() or {"host": "this host"})) from None
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:
            raise RunLocked(f"{self.path}: the lock file keeps changing; is another run starting in this folder?")
        try:
            self._take(fd)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    def _open(self) -> int:
        """An fd of the lock file, created if absent; a link or a non-plain file in its place is refused."""
        import stat

        bad = f"{self.path}: not a plain file"
        try:
            st = os.lstat(self.path)
            if not stat.S_ISREG(st.st_mode):
                raise RunLocked(f"{bad} ({'a symbolic link' if stat.S_ISLNK(st.st_mode) else 'a special file'}); "
                                f"refusing to write the run lock through it: remove it or choose another --out")
        except FileNotFoundError:
            pass
        flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
        try:
            fd = os.open(self.path, flags, 0o644)
        except OSError as e:
            if e.errno == errno.ELOOP:  # a link appeared between the lstat and the open
                raise RunLocked(f"{bad} (a symbolic link); refusing to write the run lock through it") from None
            raise
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink > 1:
            os.close(fd)
            raise RunLocked(f"{bad} ({'a hard link to another file' if stat.S_ISREG(st.st_mode) else 'a special file'}"
                            f"); refusing to write the run lock through it: remove it or choose another --out")
        return fd

    def _take(self, fd: int) -> None:
        owner = self._read(fd)
        if owner:
            host, pid = owner.get("host"), int(owner.get("pid") or 0)
            if host == _host() and pid == os.getpid():
                pass  # our own (a pipeline run twice from one process)
            elif host == _host() and pid_alive(pid):
                raise RunLocked(self._refusal(owner))
            elif host == _host():
                log.warning("%s: taking over the stale lock of a run that no longer runs (%s)", self.path,
                            describe(owner))
            elif self.force:
                log.warning("%s: --force-unlock: taking over the lock of %s", self.path, describe(owner))
            else:
                raise RunLocked(self._refusal(owner) + "; if that run is gone, run again with --force-unlock")
        record = {"pid": os.getpid(), "host": _host(),
                  "started": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
                  "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:300] if sys.argv else ""}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        os.fsync(fd)
        self.owner = record

    def _read(self, fd: int | None = None) -> dict | None:
        try:
            if fd is not None:
                text = os.pread(fd, 1 << 16, 0).decode("utf-8", "replace").strip()
            else:
                import stat

                if not stat.S_ISREG(os.lstat(self.path).st_mode):
                    return None
                fd2 = os.open(self.path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
                try:
                    text = os.pread(fd2, 1 << 16, 0).decode("utf-8", "replace").strip()
                finally:
                    os.close(fd2)
        except OSError:
            return None
        if not text:
            return None
        try:
            owner = json.loads(text)
        except json.JSONDecodeError:
            owner = None
        # unreadable: its writer died mid-write (writers hold the flock while writing), so it is stale
        return owner if isinstance(owner, dict) else {"pid": 0, "host": _host(), "started": "?"}

    def _refusal(self, owner: dict) -> str:
        return (f"{self.folder} is in use by another eligsir run: {describe(owner)} (lock file {self.path}); "
                f"wait for it to finish or choose another --out")

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            if (self._read(self._fd) or {}).get("pid") == os.getpid():
                self.path.unlink(missing_ok=True)  # before closing: no one can take a lock we still remove
        except OSError:
            pass
        finally:
            os.close(self._fd)  # drops the flock
            self._fd = None
