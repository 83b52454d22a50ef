"""Loop verification in the worker process (pose.loop_worker, pose.loop_child) and its fallback to the mapper's thread.

The worker must give the same registration as verification inline, close the synthetic room's loop as well, give
way with a RuntimeWarning (the run then verifies inline and still closes its loop) when it is killed, cannot start
or falls silent, and leave no process behind: after finish, at garbage collection, at interpreter exit, and when
its parent dies (also while it is stopped). Held while the mapper is behind, it is stopped past its time limit and
then answers. Its module must load without torch.
"""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from eligsir_o3d.pose.loop_closure import LoopClosure
from eligsir_o3d.pose.loop_worker import LoopWorker
from eligsir_o3d.pose.loops import Keyframe, keyframe_cloud, verify
from helpers import ROOT
from helpers.loop_room import LOOP, N, DriftingSource, drifted, loop_config, make_room, pose_error


@pytest.fixture(scope="module")
def room():
    return make_room()


def _settle(lc: LoopClosure, timeout: float = 60.0) -> None:
    """Let the worker finish the verification in flight: a frame period long enough for one registration, so the
    run does not depend on the machine's speed (results arrive one frame late)."""
    w = lc._worker
    t0 = time.monotonic()
    while w is not None and w.busy and w._inbox.empty() and time.monotonic() - t0 < timeout:
        time.sleep(0.005)


def _walk(room, lc: LoopClosure, each=None) -> list[np.ndarray]:
    seq, depths, poses = room
    raw = drifted(poses)
    for i in range(N):
        lc.on_frame(i, raw[i], depths[i], seq.camera)
        if each is not None:
            each(i, lc)
        _settle(lc)
    lc.finish()
    return raw


def _closed(room, lc, raw) -> None:
    after = pose_error(room[2][-1], lc.pose_of(N - 1, raw[-1]))
    assert lc.counters()["loops_accepted"] >= 1, lc.counters()
    assert after[0] < 0.01 and after[1] < 0.5, after


def _gone(pid: int, timeout: float = 30.0) -> bool:
    """The process ``pid`` has exited (a zombie counts: it runs nothing)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            with open(f"/proc/{pid}/status") as f:
                if any(line.startswith("State:") and "Z" in line.split()[1] for line in f):
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


def test_the_worker_verifies_a_pair_as_the_mapper_thread_does(room):
    seq, depths, poses = room
    cfg = loop_config()
    raw = drifted(poses)
    keys = [Keyframe(i, raw[i], keyframe_cloud(depths[i], seq.camera, cfg)) for i in range(N)]
    worker = LoopWorker(cfg)
    try:
        for k, j in ((LOOP, 0), (N - 1, 1), (40, 3)):  # the loop's closing pairs, and one that cannot register
            inline = verify(keys, raw, k, j, cfg)
            worker.submit(keys, raw, k, j)
            got, seconds = worker.result(wait=True)
            assert (got.source, got.target, got.accepted) == (k, j, inline.accepted)
            np.testing.assert_allclose(got.transform, inline.transform, atol=1e-6)
            assert got.fitness == pytest.approx(inline.fitness, abs=1e-6) and seconds > 0
            if inline.accepted:
                np.testing.assert_allclose(got.information, inline.information, rtol=1e-6, atol=1e-6)
        assert worker.sent == N and worker.cpu_seconds > 0
        assert any(verify(keys, raw, k, j, cfg).accepted for k, j in ((LOOP, 0), (N - 1, 1)))
    finally:
        worker.close()


def test_the_worker_closes_the_loop_and_ends_with_the_stream(room):
    lc = LoopClosure(loop_config(), background=True)
    procs = []
    raw = _walk(room, lc, lambda i, lc: procs.append(lc._worker.proc) if lc._worker and not procs else None)
    _closed(room, lc, raw)
    c = lc.counters()
    assert c["worker"] == "process" and c["worker_failure"] is None, c
    assert c["worker_seconds"] > 0 and c["worker_cpu_seconds"] > 0, c
    assert lc._worker is None and procs and procs[0].poll() is not None  # finish ended the process


def _stopped(pid: int, timeout: float = 10.0) -> bool:
    """The process ``pid`` shows as stopped (a signal takes effect when the process is next scheduled)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        with open(f"/proc/{pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] == "T":
                return True
        time.sleep(0.01)
    return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_held_worker_is_stopped_past_its_time_limit_and_then_answers(room):
    seq, depths, poses = room
    cfg = loop_config()
    raw = drifted(poses)
    keys = [Keyframe(i, raw[i], keyframe_cloud(depths[i], seq.camera, cfg)) for i in range(N)]
    worker = LoopWorker(cfg, timeout_s=1.0)
    try:
        worker.submit(keys, raw, LOOP, 0)
        worker.hold(True)
        assert not worker.held  # not before the child says it is ready (and dies with its parent)
        assert worker._ready.wait(60)
        worker.hold(True)
        assert worker.held and _stopped(worker.proc.pid)
        time.sleep(1.5)  # past timeout_s: a stopped child is not a silent one
        assert worker.result() is None and worker.held
        got, _ = worker.result(wait=True)  # waiting lets it go on
        assert not worker.held and worker.held_seconds >= 1.5
        np.testing.assert_allclose(got.transform, verify(keys, raw, LOOP, 0, cfg).transform, atol=1e-6)
        worker.hold(True)
        pid = worker.proc.pid
    finally:
        worker.close()
    assert _gone(pid)  # closing lets a stopped child go on to its end


def test_the_worker_is_held_while_the_mapper_is_behind(room):
    seq, depths, poses = room
    raw = drifted(poses)
    lc = LoopClosure(loop_config(), background=True, hold_backlog=2)
    i = 0
    while lc._worker is None:
        lc.on_frame(i, raw[i], depths[i], seq.camera)
        i += 1
    assert lc._worker._ready.wait(60)
    for backlog, held in ((2, True), (1, True), (3, True), (0, False), (1, False)):
        lc.set_load(backlog)
        assert lc._worker.held is held, backlog
    lc.set_load(2)
    time.sleep(0.2)
    lc.finish()  # waits: the worker goes on
    assert lc.counters()["worker_held_seconds"] >= 0.2
    never = LoopClosure(loop_config(), background=True, hold_backlog=0)
    never.on_frame(0, raw[0], depths[0], seq.camera)
    never.set_load(4)
    assert never._worker is None or not never._worker.held
    never.finish()


def test_a_checkpoint_keeps_the_candidate_the_worker_is_verifying(room):
    seq, depths, poses = room
    lc = LoopClosure(loop_config(), background=True)
    raw = drifted(poses)
    i = 0
    while lc._job is None:
        lc.on_frame(i, raw[i], depths[i], seq.camera)
        i += 1
    running = list(lc._job)
    assert lc.state_dict()["pending"][0] == running  # re-verified after a resume, not lost
    lc.finish()


def test_a_killed_worker_gives_way_to_verification_inline(room):
    lc = LoopClosure(loop_config(), background=True)
    killed = []

    def kill(i, lc):
        if not killed and lc._worker is not None and lc._job is not None:
            os.kill(lc._worker.proc.pid, signal.SIGKILL)
            lc._worker.proc.wait()
            killed.append(lc._job)

    with pytest.warns(RuntimeWarning, match="exited"):
        raw = _walk(room, lc, kill)
    assert killed
    c = lc.counters()
    assert c["worker"] == "inline" and "exited" in c["worker_failure"], c
    assert any((r["frame"], r["with"]) == killed[0] for r in lc.log)  # the candidate it held was verified here
    _closed(room, lc, raw)


def test_a_worker_that_cannot_start_gives_way(room, monkeypatch):
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    lc = LoopClosure(loop_config(), background=True)
    with pytest.warns(RuntimeWarning, match="did not start"):
        raw = _walk(room, lc)
    assert "did not start" in lc.counters()["worker_failure"]
    _closed(room, lc, raw)


def test_a_silent_worker_gives_way(room):
    lc = LoopClosure(loop_config(), background=True)
    lc._worker = LoopWorker(lc.cfg, timeout_s=0.02)  # less than the process takes to start
    seq, depths, poses = room
    raw = drifted(poses)
    with pytest.warns(RuntimeWarning, match="no reply in 0.02 s"):
        for i in range(N):
            lc.on_frame(i, raw[i], depths[i], seq.camera)
            time.sleep(0.005)
        lc.finish()
    _closed(room, lc, raw)


def test_garbage_collection_ends_the_worker(room):
    seq, depths, poses = room
    lc = LoopClosure(loop_config(), background=True)
    raw = drifted(poses)
    i = 0
    while lc._worker is None:
        lc.on_frame(i, raw[i], depths[i], seq.camera)
        i += 1
    proc = lc._worker.proc
    del lc
    gc.collect()
    assert proc.poll() is not None


_SCRIPT = """
import os, sys
from eligsir_o3d.pose.loop_worker import LoopWorker
from eligsir_o3d.pose.loops import LoopConfig
w = LoopWorker(LoopConfig())
w._start()
if sys.argv[1] == "held":
    assert w._ready.wait(60)
    w.hold(True)
    assert w.held
print(w.proc.pid, flush=True)
os._exit(0) if sys.argv[1] in ("die", "held") else sys.exit(0)
"""


@pytest.mark.parametrize("how", ["exit", "die", "held"])  # interpreter exit (atexit), the parent killed (stdin EOF),
# the parent killed while the child is stopped (it cannot read its input: Linux's parent-death signal)
def test_no_worker_outlives_its_parent(how):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
    out = subprocess.run([sys.executable, "-c", _SCRIPT, how], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert _gone(int(out.stdout.split()[0]))


def test_the_worker_module_loads_without_torch():
    code = ("import sys, eligsir_o3d.pose.loop_worker, eligsir_o3d.pose.loop_child; "
            "assert 'torch' not in sys.modules, 'torch loaded'")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr



def test_a_mapping_run_outlives_its_worker(room):
    """A tracked Reconstructor verifying in the worker process: the worker is killed mid-run; the run goes on,
    closes its loop verifying inline, and the map follows; nothing is left running after finalize."""
    from eligsir_o3d import Reconstructor
    from eligsir_o3d.config import Config

    seq, _, poses = room
    cfg = Config()
    cfg.loops.detect, cfg.loops.background, cfg.clock.updates_per_frame = loop_config(), "on", 1
    rec = Reconstructor(seq.intrinsic, "cpu", cfg, pose_source=DriftingSource(drifted(poses)),
                        depth_scale=seq.depth_scale)
    killed = []
    with pytest.warns(RuntimeWarning, match="exited"):
        for i in range(N):
            rec.integrate(seq[i % LOOP].rgbd, None, timestamp=i / 30.0)
            worker = rec.loops._worker
            if not killed and worker is not None and worker.busy:
                worker.proc.kill()
                worker.proc.wait()
                killed.append(worker.proc)
            _settle(rec.loops)
        rec.finalize()
    c = rec.loops.counters()
    assert killed and c["worker"] == "inline" and c["loops_accepted"] >= 1 and c["optimisations"] >= 1, c
    assert rec.loops._worker is None and len(rec.gmap) > 0
    for view in rec.views.views:  # the retained views took the corrected poses
        np.testing.assert_allclose(view.T_world_cam, rec.loops.pose_of(view.index, None), atol=1e-9)
