"""One results folder, one run (issue 14, item 3): a second run on the same --out refuses while the first holds
OUT/eligsir.lock, a stale lock is taken over, and --resume refuses a folder made with another config, held-out
split or pose source, naming what differs, while a resume with the same settings continues."""

import json
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

import eligsir_o3d
from eligsir_o3d.run.pipeline import MappingPipeline, run_mapping
from eligsir_o3d.run.resume import ResumeMismatch, config_differences
from eligsir_o3d.run.lock import LOCK_FILE, RunLock, RunLocked, pid_alive
from helpers.small_runs import quick_config, quick_options


_cfg, _opts = quick_config, quick_options


def _lock(folder, pid, host=None):
    folder.mkdir(parents=True, exist_ok=True)
    record = {"pid": pid, "host": host or socket.gethostname(), "started": "2026-11-29 20:00:00 UTC",
              "command": "eligsir map synthetic --out x"}
    (folder / LOCK_FILE).write_text(json.dumps(record))
    return record


@pytest.fixture
def live_pid():
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    yield child.pid
    child.kill()
    child.wait()


@pytest.fixture
def dead_pid():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()  # exited and reaped: no such process any more
    assert not pid_alive(child.pid)
    return child.pid


def test_a_second_run_on_the_same_out_is_refused_naming_the_first(tmp_path, live_pid):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    _lock(tmp_path, live_pid)
    (tmp_path / "map.ply").write_text("the first run's map")
    with pytest.raises(RunLocked, match=rf"in use by another eligsir run: pid {live_pid} on host "
                                        rf"{socket.gethostname()}, started 2026-11-29 20:00:00 UTC"):
        run_mapping("synthetic", tmp_path, _cfg(), _opts())
    r = CliRunner().invoke(app, ["map", "synthetic", "--max-frames", "10", "--out", str(tmp_path), "-q"])
    assert r.exit_code == 4 and f"pid {live_pid}" in r.output and "Traceback" not in r.output, r.output
    assert len([ln for ln in r.output.splitlines() if ln.strip()]) == 1, r.output
    assert (tmp_path / "map.ply").read_text() == "the first run's map"  # nothing of the first run touched
    assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == live_pid  # its lock neither


def test_a_lock_held_right_now_is_refused_and_released_after_the_run(tmp_path):
    with RunLock(tmp_path) as first:  # this process holds it (flock and record)
        assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()
        with pytest.raises(RunLocked, match=f"pid {os.getpid()}"):
            RunLock(tmp_path).acquire()
        assert first.owner["pid"] == os.getpid()
    assert not (tmp_path / LOCK_FILE).exists()
    code = ("import sys, time; from eligsir_o3d.run.lock import RunLock\n"
            "with RunLock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(Path(eligsir_o3d.__file__).parents[1])})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunLocked, match=f"pid {holder.pid}"):
            RunLock(tmp_path).acquire()
    finally:
        holder.kill()
        holder.wait()
    with RunLock(tmp_path):  # SIGKILLed: its lock is stale now, and taken over
        pass


def test_a_stale_lock_of_a_dead_process_is_taken_over_with_a_warning(tmp_path, dead_pid, caplog):
    _lock(tmp_path, dead_pid)
    with caplog.at_level(logging.WARNING, logger="eligsir_o3d"):
        m = run_mapping("synthetic", tmp_path, _cfg(), _opts())
    assert m["frames_source"] == 8 and (tmp_path / "metrics.json").is_file()
    assert f"taking over the stale lock of a run that no longer runs (pid {dead_pid}" in caplog.text
    assert not (tmp_path / LOCK_FILE).exists()  # released at the end


def test_another_hosts_lock_is_respected_unless_forced(tmp_path, caplog):
    _lock(tmp_path, 1, host="other-host.example")
    with pytest.raises(RunLocked, match="pid 1 on host other-host.example.*--force-unlock"):
        RunLock(tmp_path).acquire()
    with caplog.at_level(logging.WARNING, logger="eligsir_o3d"), RunLock(tmp_path, force=True):
        assert json.loads((tmp_path / LOCK_FILE).read_text())["host"] == socket.gethostname()
    assert "--force-unlock: taking over the lock of pid 1 on host other-host.example" in caplog.text


@pytest.mark.parametrize("fault", [KeyboardInterrupt, ValueError])
def test_the_lock_is_released_on_error_and_interrupt(tmp_path, monkeypatch, fault):
    def stream(self):
        assert json.loads((tmp_path / LOCK_FILE).read_text())["pid"] == os.getpid()  # held while running
        raise fault("stopped")

    monkeypatch.setattr(MappingPipeline, "stream", stream)
    with pytest.raises(fault):
        run_mapping("synthetic", tmp_path, _cfg(), _opts())
    assert not (tmp_path / LOCK_FILE).exists()


@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory):
    """A results folder with a checkpoint (a run of 10 frames, held out every 5th, checkpoints every 3)."""
    out = tmp_path_factory.mktemp("resume") / "run"
    run_mapping("synthetic", out, _cfg(), _opts(checkpoint_every=3))
    assert (out / "checkpoint.pt").is_file()
    return out


def _copy(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_resume_with_another_config_is_refused_naming_the_key(tmp_path, checkpointed):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    out = _copy(checkpointed, tmp_path / "run")
    cfg = _cfg()
    cfg.optim.lrs.means = 0.001
    with pytest.raises(ResumeMismatch, match=rf"--resume: {out} was made with optim.lrs.means=0.0005 \(now 0.001\)"):
        run_mapping("synthetic", out, cfg, _opts(checkpoint_every=3, resume=True))
    r = CliRunner().invoke(app, ["map", "synthetic", "--max-frames", "10", "--holdout-every", "5", "--eval-every",
                                 "0", "--updates-per-frame", "3", "--renderer", "torch", "--checkpoint-every", "3",
                                 "--resume", "--out", str(out), "-q"])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert f"--resume: {out} was made with" in r.output and "clock.updates_per_frame=2 (now 3)" in r.output, r.output
    assert not (out / "eligsir.lock").exists()


@pytest.mark.parametrize("change, said", [
    (dict(holdout_every=4), "a different held-out split: 2 held-out frames then, 2 now (held out only then: 7; "
                            "only now: 6)"),
    (dict(max_frames=14), "a different held-out split: 2 held-out frames then, 3 now (held out only then: none; "
                          "only now: 12)"),
    (dict(pose="odometry"), "--pose 'gt' (now 'odometry')"),
])
def test_resume_with_another_split_or_pose_is_refused(tmp_path, checkpointed, change, said):
    out = _copy(checkpointed, tmp_path / "run")
    with pytest.raises(ResumeMismatch) as e:
        run_mapping("synthetic", out, _cfg(), _opts(checkpoint_every=3, resume=True, **change))
    assert str(e.value).startswith(f"--resume: {out} was made with {said}"), str(e.value)


def test_a_resume_with_the_same_settings_continues(tmp_path, checkpointed, caplog):
    out = _copy(checkpointed, tmp_path / "run")
    first = json.loads((out / "metrics.json").read_text())
    cfg = _cfg()
    cfg.clock.on_bad_frame = "stop"  # how bad frames are handled from now on: allowed, and applied
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        m = run_mapping("synthetic", out, cfg, _opts(checkpoint_every=3, resume=True))
    assert "resuming" in caplog.text and "at source frame 6 of 8" in caplog.text
    assert m["frames_released"] < first["frames_released"] and m["frames_source"] == first["frames_source"]
    assert json.loads((out / "config.json").read_text())["clock"]["on_bad_frame"] == "stop"


def test_config_differences_ignore_where_a_run_executes_and_a_calibrated_cost_model():
    saved = _cfg().resolve().to_dict()
    now = _cfg()
    now.device, now.clock.on_bad_frame, now.clock.cost_source = "cpu", "stop", "calibrate"
    now.clock.cost.update_s = 1.0  # the run keeps the model it calibrated when it started
    assert config_differences(saved, now.resolve().to_dict()) == []
    now.clock.cost_source = "config"  # an explicit cost model is compared
    assert [k for k, _, _ in config_differences(saved, now.resolve().to_dict())] == ["clock.cost.update_s"]
    other = _cfg()
    other.seed, other.ablate = 3, ("views",)
    assert config_differences(saved, other.resolve().to_dict()) == [("ablate", [], ["views"]), ("seed", 0, 3)]
