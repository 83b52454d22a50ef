"""The loop-closure worker's own side (:class:`.loop_worker.LoopWorker` is the mapper's handle): the process
``python -m eligsir_o3d.pose.loop_child NICE CPUS`` and the messages both sides exchange.

Messages are pickled and length-prefixed (:func:`write_message`, :func:`read_message`). The child lowers its
priority (``nice``; at 19 also the idle scheduling class), keeps to the last ``cpus`` of its CPUs (0: all), arms
Linux's parent-death signal and says it is ready, then serves: keyframes arrive once (clouds, or inputs to build,
answered with what was built), verifications reply with their result, until its input ends. It imports neither
torch nor the mapper; Open3D loads when it starts serving.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import sys

from .loops import Keyframe, LoopConfig

_HEADER = struct.Struct("<Q")  # the byte length of the pickled message that follows


def write_message(stream, message) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)))
    stream.write(data)
    stream.flush()


def read_message(stream):
    """The next message, or None at end of input."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    size = _HEADER.unpack(head)[0]
    data = stream.read(size)
    return None if len(data) < size else pickle.loads(data)


def _lower_priority(nice: int) -> None:
    """``nice`` the process; at 19, also the idle scheduling class (a waking thread of the mapper then takes its
    CPU at once rather than at the end of the child's time slice)."""
    try:
        os.nice(nice)
        if nice >= 19 and hasattr(os, "SCHED_IDLE"):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def _confine(cpus: int) -> None:
    """Run on the last ``cpus`` of the CPUs this process may use (0: all of them). Open3D's thread pool sizes
    itself from this set when it starts, so the child's registrations then keep to those CPUs."""
    if cpus <= 0 or not hasattr(os, "sched_setaffinity"):
        return
    try:
        allowed = sorted(os.sched_getaffinity(0))
        if cpus < len(allowed):
            os.sched_setaffinity(0, allowed[-cpus:])
    except OSError:
        pass


def _die_with_parent() -> bool:
    """Linux: the child is killed when the mapper's process ends, even while it is stopped (:meth:`LoopWorker.hold`)
    and cannot read the end of its input. True where that is armed."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL)) == 0  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


def _cpu_seconds() -> float:
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def serve(inp, out) -> None:
    """The child's loop: keyframes arrive once (clouds, or inputs to build, answered with what was built),
    verifications reply with their result; every reply carries its seconds and the child's CPU seconds so far;
    returns at end of input."""
    import traceback

    import open3d as o3d

    from .loops import keyframe_data, timed_verify

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    keys: list[Keyframe] = []
    cfg = LoopConfig()
    while (message := read_message(inp)) is not None:
        kind = message[0]
        if kind == "config":
            cfg = message[1]
        elif kind in ("keyframe", "build"):
            if kind == "keyframe":
                _, index, raw_pose, points, normals = message
                cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
                cloud.normals = o3d.utility.Vector3dVector(normals)
            else:
                _, k, index, raw_pose, strided, intr = message
                cloud = None
            keys.append(Keyframe(int(index), raw_pose, cloud))
            old = len(keys) - 1 - cfg.local - 2  # local maps are rebuilt on demand: keep the recent ones cached
            if old >= 0:
                keys[old].local_cloud = None
            if kind == "build":
                try:
                    if k != len(keys) - 1:
                        raise IndexError(f"keyframe {k} built as the child's keyframe {len(keys) - 1}")
                    data = keyframe_data(keys, k, strided, intr, cfg)
                except Exception:  # noqa: BLE001 - reported to the mapper, which builds on its own thread
                    write_message(out, ("error", k, traceback.format_exc(limit=3)))
                    continue
                write_message(out, ("built", k, data, data.seconds, _cpu_seconds()))
        elif kind == "verify":
            _, number, k, j, poses = message
            try:
                result, seconds = timed_verify(keys, poses, k, j, cfg)
            except Exception:  # noqa: BLE001 - reported to the mapper, which verifies on its own thread
                write_message(out, ("error", number, traceback.format_exc(limit=3)))
                continue
            write_message(out, ("result", number, result, seconds, _cpu_seconds()))


def main() -> None:
    _lower_priority(int(sys.argv[1]) if len(sys.argv) > 1 else 19)
    _confine(int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    armed = _die_with_parent()
    out = os.fdopen(os.dup(1), "wb")  # the replies' own pipe: C++ code printing to stdout goes to stderr instead
    os.dup2(2, 1)
    write_message(out, ("ready", armed))
    serve(sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
