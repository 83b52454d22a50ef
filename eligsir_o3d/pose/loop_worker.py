"""Loop verification in a separate process: no GIL shared with the mapper, at the lowest CPU priority.

:class:`LoopWorker` is the mapper's handle. On its first :meth:`~LoopWorker.submit` it starts
``python -m eligsir_o3d.pose.loop_worker`` (this module, which imports neither torch nor the mapper) at nice 19,
with one OpenMP/BLAS thread. Messages are pickled, length-prefixed, over the child's stdin and stdout; two daemon
threads of the mapper's process write and read them, so :meth:`~LoopWorker.submit` and
:meth:`~LoopWorker.result` never block on the pipe. Each keyframe's cloud crosses once (points and normals); a
verification then names its two keyframes by position and carries their current pose estimates. The child builds
local maps and registers them with :func:`.loops.verify`, exactly as the mapper's thread would.

A worker that cannot start, dies, or leaves a reply more than ``timeout_s`` late raises :class:`WorkerFailed` from
:meth:`~LoopWorker.result` (the caller then verifies on its own thread). The child exits at end of input: when
:meth:`~LoopWorker.close` runs (also at garbage collection and at interpreter exit) or when the parent dies.
"""

from __future__ import annotations

import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import time
import weakref
from pathlib import Path

import numpy as np

from .loops import Keyframe, LoopConfig, LoopResult

_HEADER = struct.Struct("<Q")  # the byte length of the pickled message that follows
_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
_EOF = ("eof",)


class WorkerFailed(RuntimeError):
    """The verification process is gone or late; the message says what happened."""


def _write(stream, message) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)))
    stream.write(data)
    stream.flush()


def _read(stream):
    """The next message, or None at end of input."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    size = _HEADER.unpack(head)[0]
    data = stream.read(size)
    return None if len(data) < size else pickle.loads(data)


def _writer(stream, outbox: queue.Queue) -> None:
    try:
        while (message := outbox.get()) is not None:
            _write(stream, message)
    except Exception:  # noqa: BLE001 - the child is gone or a message would not pickle: its input ends
        pass
    finally:
        try:
            stream.close()
        except OSError:
            pass


def _reader(stream, inbox: queue.Queue) -> None:
    try:
        while (message := _read(stream)) is not None:
            inbox.put(message)
    except Exception:  # noqa: BLE001 - a broken pipe or message: reported as the end, the mapper verifies inline
        pass
    inbox.put(_EOF)


def _stop(proc: subprocess.Popen, outbox: queue.Queue) -> None:
    """End the child: close its input (it exits), then kill it if it has not after a moment."""
    outbox.put(None)
    try:
        proc.wait(timeout=3.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class LoopWorker:
    """The mapper's side of the verification process; one verification in flight at a time."""

    def __init__(self, cfg: LoopConfig, timeout_s: float = 60.0):
        self.cfg, self.timeout_s = cfg, float(timeout_s)
        self.proc: subprocess.Popen | None = None
        self.sent = 0  # keyframes the child holds (the first ``sent`` of the list)
        self.cpu_seconds = 0.0  # the child's CPU time (user + system), as it last reported
        self._outbox: queue.Queue = queue.Queue()
        self._inbox: queue.Queue = queue.Queue()
        self._job: tuple[int, float] | None = None  # (job number, when it was submitted)
        self._jobs = 0
        self._closer = None

    def _start(self) -> None:
        env = dict(os.environ, **_ENV)
        root = str(Path(__file__).resolve().parents[2])  # the child imports this very package
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "eligsir_o3d.pose.loop_worker"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, env=env, close_fds=True)
        except OSError as e:
            raise WorkerFailed(f"the loop verification process did not start ({e})") from e
        for target, stream, box in ((_writer, self.proc.stdin, self._outbox), (_reader, self.proc.stdout, self._inbox)):
            threading.Thread(target=target, args=(stream, box), name="eligsir-loops-io", daemon=True).start()
        self._closer = weakref.finalize(self, _stop, self.proc, self._outbox)  # also runs at interpreter exit
        self._outbox.put(("config", self.cfg))

    def submit(self, keys: list[Keyframe], poses: list[np.ndarray], k: int, j: int) -> None:
        """Hand the child the verification of keyframe ``k`` against ``j`` at the estimates ``poses`` (it gets
        the keyframes it has not seen first); returns at once."""
        if self._job is not None:
            raise RuntimeError("a verification is already in flight")
        if self.proc is None:
            self._start()
        for key in keys[self.sent:]:
            self._outbox.put(("keyframe", key.index, key.raw_pose, np.asarray(key.cloud.points),
                              np.asarray(key.cloud.normals)))
        self.sent = len(keys)
        self._jobs += 1
        self._outbox.put(("verify", self._jobs, k, j, {k: poses[k].copy(), j: poses[j].copy()}))
        self._job = (self._jobs, time.monotonic())

    @property
    def busy(self) -> bool:
        """A verification is in flight."""
        return self._job is not None

    def result(self, wait: bool = False) -> tuple[LoopResult, float] | None:
        """The finished verification and its seconds in the child, or None while it runs (``wait``: block for
        it, up to the time limit). Raises :class:`WorkerFailed` when the child died or is over the limit."""
        if self._job is None:
            return None
        job, t0 = self._job
        while True:
            left = t0 + self.timeout_s - time.monotonic()
            try:
                message = self._inbox.get(timeout=max(left, 0.0)) if wait else self._inbox.get_nowait()
            except queue.Empty:
                if left > 0 and not wait:
                    return None
                raise WorkerFailed(f"the loop verification process gave no reply in {self.timeout_s:g} s") from None
            if message[0] == "eof":
                code = self.proc.poll() if self.proc is not None else None
                raise WorkerFailed(f"the loop verification process exited (code {code})")
            if message[0] == "error":
                raise WorkerFailed(f"the loop verification process failed: {message[2]}")
            _, number, result, seconds, self.cpu_seconds = message
            if number == job:
                self._job = None
                return result, seconds

    def close(self, kill: bool = False) -> None:
        """End the child (waits a moment for it to exit; ``kill``: at once); the handle can start a new one
        afterwards."""
        if kill and self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self._closer is not None:
            self._closer()
        self.proc, self.sent, self._job, self._closer = None, 0, None, None
        self._outbox, self._inbox = queue.Queue(), queue.Queue()


# ---- the child ----------------------------------------------------------------------------------------------
def _lowest_priority() -> None:
    try:
        os.nice(19)
    except (AttributeError, OSError):
        pass


def _cpu_seconds() -> float:
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def serve(inp, out) -> None:
    """The child's loop: keyframes arrive once, verifications reply with their result, seconds and the child's
    CPU seconds so far; returns at end of input."""
    import traceback

    import open3d as o3d

    from .loops import timed_verify

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    keys: list[Keyframe] = []
    cfg = LoopConfig()
    while (message := _read(inp)) is not None:
        kind = message[0]
        if kind == "config":
            cfg = message[1]
        elif kind == "keyframe":
            _, index, raw_pose, points, normals = message
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            cloud.normals = o3d.utility.Vector3dVector(normals)
            keys.append(Keyframe(int(index), raw_pose, cloud))
            old = len(keys) - 1 - cfg.local - 2  # local maps are rebuilt on demand: keep the recent ones cached
            if old >= 0:
                keys[old].local_cloud = None
        elif kind == "verify":
            _, number, k, j, poses = message
            try:
                result, seconds = timed_verify(keys, poses, k, j, cfg)
            except Exception:  # noqa: BLE001 - reported to the mapper, which verifies on its own thread
                _write(out, ("error", number, traceback.format_exc(limit=3)))
                continue
            _write(out, ("result", number, result, seconds, _cpu_seconds()))


def main() -> None:
    _lowest_priority()
    out = os.fdopen(os.dup(1), "wb")  # the replies' own pipe: C++ code printing to stdout goes to stderr instead
    os.dup2(2, 1)
    serve(sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
