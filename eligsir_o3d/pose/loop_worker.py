"""The loop-closure worker: a separate process (no GIL shared with the mapper, at a lower CPU priority) that
builds keyframes and verifies loop candidates.

:class:`LoopWorker` is the mapper's handle. On first use it starts ``python -m eligsir_o3d.pose.loop_child``
(:mod:`.loop_child`, which imports neither torch nor the mapper) at the handle's ``nice`` (19 by default: the
lowest priority, and the idle scheduling class) on the handle's ``cpus`` (0: all), with one OpenMP/BLAS thread.
Messages are pickled, length-prefixed, over the child's stdin and stdout;
two daemon threads of the mapper's process write and read them, so no call blocks on the pipe unless asked to
wait. :meth:`~LoopWorker.build` hands the child a
keyframe's strided depth, intrinsics and tracker pose; the child builds its cloud and its odometry edge from the
previous keyframe (:func:`.loops.keyframe_data`) and answers with them, in order. A verification names its two
keyframes by position and carries their current pose estimates; the child builds local maps and registers them
with :func:`.loops.verify`. Keyframes built on the mapper's side cross once, as clouds (points and normals). The
child computes exactly what the mapper's thread would.

While the mapper is behind its stream the handle can stop the child outright (:meth:`~LoopWorker.hold`, SIGSTOP
and SIGCONT), once the child has said it is ready and dies with its parent (Linux's parent-death signal, sent
when the thread that started it ends), so a stopped child never outlives the mapper; elsewhere it is never
stopped.

A worker that cannot start, dies, fails, or gives no reply for ``timeout_s`` while work is in flight raises
:class:`WorkerFailed` from :meth:`~LoopWorker.built` and :meth:`~LoopWorker.result` (the caller then works on its
own thread). The child exits at end of input: when :meth:`~LoopWorker.close` runs (also at garbage collection and
at interpreter exit) or when the parent dies.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
import weakref
from pathlib import Path

import numpy as np

from .loop_child import read_message, write_message
from .loops import Keyframe, KeyframeData, LoopConfig, LoopResult

_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
_EOF = ("eof",)


class WorkerFailed(RuntimeError):
    """The verification process is gone or late; the message says what happened."""


def _writer(stream, outbox: queue.Queue) -> None:
    try:
        while (message := outbox.get()) is not None:
            write_message(stream, message)
    except Exception:  # noqa: BLE001 - the child is gone or a message would not pickle: its input ends
        pass
    finally:
        try:
            stream.close()
        except OSError:
            pass


def _reader(stream, inbox: queue.Queue, ready: threading.Event) -> None:
    try:
        while (message := read_message(stream)) is not None:
            if message[0] == "ready":
                if message[1]:  # it dies with its parent: it may be stopped
                    ready.set()
                continue
            inbox.put(message)
    except Exception:  # noqa: BLE001 - a broken pipe or message: reported as the end, the mapper verifies inline
        pass
    inbox.put(_EOF)


def _stop(proc: subprocess.Popen, outbox: queue.Queue) -> None:
    """End the child: close its input (it exits; a stopped child is let go on first), then kill it if it has not
    after a moment."""
    outbox.put(None)
    if hasattr(signal, "SIGCONT") and proc.poll() is None:
        try:
            os.kill(proc.pid, signal.SIGCONT)
        except OSError:
            pass
    try:
        proc.wait(timeout=3.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class LoopWorker:
    """The mapper's side of the worker process: keyframe builds (any number in flight, answered in order) and one
    verification in flight at a time."""

    def __init__(self, cfg: LoopConfig, timeout_s: float = 60.0, nice: int = 19, cpus: int = 0):
        self.cfg, self.timeout_s, self.nice, self.cpus = cfg, float(timeout_s), int(nice), int(cpus)
        self.proc: subprocess.Popen | None = None
        self.sent = 0  # keyframes the child holds or builds (the first ``sent`` of the list)
        self.cpu_seconds = 0.0  # the child's CPU time (user + system), as it last reported
        self._outbox: queue.Queue = queue.Queue()
        self._inbox: queue.Queue = queue.Queue()
        self._job: tuple[int, float] | None = None  # the verification in flight: (job number, when submitted)
        self._jobs = 0
        self._builds: set[int] = set()  # keyframes whose build is in flight
        self._built: dict[int, KeyframeData] = {}  # finished builds not yet taken
        self._done: tuple | None = None  # the finished verification: (job number, result, seconds)
        self._since = 0.0  # the last reply, or the submission that found nothing in flight
        self._held: float | None = None  # when the child was stopped (:meth:`hold`), None while it runs
        self.held_seconds = 0.0  # how long the child was stopped, all told
        self._ready = threading.Event()  # the child said it runs (and dies with its parent): it may be stopped
        self._closer = None

    def _start(self) -> None:
        env = dict(os.environ, **_ENV)
        root = str(Path(__file__).resolve().parents[2])  # the child imports this very package
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "eligsir_o3d.pose.loop_child", str(self.nice),
                                          str(self.cpus)],
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, close_fds=True)
        except OSError as e:
            raise WorkerFailed(f"the loop verification process did not start ({e})") from e
        for target, args in ((_writer, (self.proc.stdin, self._outbox)),
                             (_reader, (self.proc.stdout, self._inbox, self._ready))):
            threading.Thread(target=target, args=args, name="eligsir-loops-io", daemon=True).start()
        self._closer = weakref.finalize(self, _stop, self.proc, self._outbox)  # also runs at interpreter exit
        self._outbox.put(("config", self.cfg))

    def _send(self, keys: list[Keyframe], upto: int) -> None:
        """Start the child if needed and hand it the clouds of ``keys[sent:upto]`` (built on the mapper's side)."""
        if self.proc is None:
            self._start()
        if not self.busy:
            self._since = time.monotonic()
        for key in keys[self.sent:upto]:
            self._outbox.put(("keyframe", key.index, key.raw_pose, np.asarray(key.cloud.points),
                              np.asarray(key.cloud.normals)))
        self.sent = max(self.sent, upto)

    def build(self, keys: list[Keyframe], k: int, strided: np.ndarray, intr: tuple) -> None:
        """Hand the child keyframe ``k``'s inputs (:func:`.loops.strided_depth`, :func:`.loops.intrinsics`): it
        builds the cloud and the odometry edge from ``k - 1`` (:func:`.loops.keyframe_data`); returns at once.
        The keyframes before ``k`` the child lacks are sent first (their clouds must be built)."""
        if k < self.sent:
            raise RuntimeError(f"keyframe {k} is already in the worker")
        self._send(keys, k)
        key = keys[k]
        self._outbox.put(("build", k, key.index, key.raw_pose, strided, intr))
        self._builds.add(k)
        self.sent = k + 1

    def submit(self, keys: list[Keyframe], poses: list[np.ndarray], k: int, j: int) -> None:
        """Hand the child the verification of keyframe ``k`` against ``j`` at the estimates ``poses`` (it gets
        the keyframes up to ``k`` it has not seen first); returns at once."""
        if self._job is not None:
            raise RuntimeError("a verification is already in flight")
        self._send(keys, max(k, j) + 1)
        self._jobs += 1
        self._outbox.put(("verify", self._jobs, k, j, {k: poses[k].copy(), j: poses[j].copy()}))
        self._job = (self._jobs, time.monotonic())

    def hold(self, stop: bool) -> None:
        """Stop the child (``stop``) or let it go on: while the mapper is behind its stream the child takes no CPU
        at all, not even what the idle scheduling class leaves it (a stopped child's time does not count toward
        ``timeout_s``). Does nothing where the platform has no SIGSTOP, no child runs, or the child has not said
        it is ready (until then it could not die with its parent)."""
        if self.proc is None or not hasattr(signal, "SIGSTOP") or stop == (self._held is not None):
            return
        if stop and not self._ready.is_set():
            return
        try:
            os.kill(self.proc.pid, signal.SIGSTOP if stop else signal.SIGCONT)
        except OSError:  # the child is gone: the next reply-wait reports it
            return
        if stop:
            self._held = time.monotonic()
        else:
            held = time.monotonic() - self._held
            self._since += held
            self.held_seconds += held
            self._held = None

    @property
    def held(self) -> bool:
        """The child is stopped by :meth:`hold`."""
        return self._held is not None

    @property
    def busy(self) -> bool:
        """A build or a verification is in flight."""
        return self._job is not None or bool(self._builds)

    def _pump(self, ready, wait: bool) -> None:
        """File the child's replies until ``ready()`` (``wait``: block for it, up to the time limit) or, without
        ``wait``, until none is left. Raises :class:`WorkerFailed` when the child died, failed, or gave no reply
        within ``timeout_s`` while work was in flight. Waiting lets a held child go on; without ``wait`` a held
        child's replies so far are filed."""
        if wait:
            self.hold(False)
        while not ready() and self.busy:
            left = self._since + self.timeout_s - time.monotonic()
            try:
                message = self._inbox.get(timeout=max(left, 0.0)) if wait else self._inbox.get_nowait()
            except queue.Empty:
                if (left > 0 or self.held) and not wait:
                    return
                raise WorkerFailed(f"the loop verification process gave no reply in {self.timeout_s:g} s") from None
            if message[0] == "eof":
                code = self.proc.poll() if self.proc is not None else None
                raise WorkerFailed(f"the loop verification process exited (code {code})")
            if message[0] == "error":
                raise WorkerFailed(f"the loop verification process failed: {message[2]}")
            self._since = time.monotonic()
            kind, number, payload, seconds, self.cpu_seconds = message
            if kind == "built":
                self._builds.discard(number)
                self._built[number] = payload
            elif self._job is not None and number == self._job[0]:
                self._job, self._done = None, (number, payload, seconds)

    def built(self, k: int, wait: bool = False) -> KeyframeData | None:
        """Keyframe ``k``'s finished build (taken: asked again, None), or None while it runs (``wait``: block for
        it). Raises :class:`WorkerFailed` as :meth:`result` does."""
        self._pump(lambda: k in self._built or k not in self._builds, wait)
        return self._built.pop(k, None)

    def result(self, wait: bool = False) -> tuple[LoopResult, float] | None:
        """The finished verification and its seconds in the child, or None while it runs (``wait``: block for
        it, up to the time limit). Raises :class:`WorkerFailed` when the child died or is over the limit."""
        self._pump(lambda: self._done is not None or self._job is None, wait)
        done, self._done = self._done, None
        return None if done is None else done[1:]

    def close(self, kill: bool = False) -> None:
        """End the child (waits a moment for it to exit; ``kill``: at once); the handle can start a new one
        afterwards."""
        if kill and self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        self.hold(False)
        if self._closer is not None:
            self._closer()
        self.proc, self.sent, self._job, self._closer, self._done, self._held = None, 0, None, None, None, None
        self._builds, self._built = set(), {}
        self._outbox, self._inbox, self._ready = queue.Queue(), queue.Queue(), threading.Event()
