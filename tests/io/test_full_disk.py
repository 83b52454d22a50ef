"""A full disk while writing a results folder (issue 14, item 2): the disk is made to report ENOSPC for chosen
files (the fsync of their temporary file fails, as a full disk with delayed allocation does), at each stage -
periodic checkpoint, map.ply, config.json, metrics.json, pictures. What was on disk before stays intact and
loadable, what can still be written is, a failed periodic checkpoint does not stop mapping, and the command ends
with one error line (exit status 3)."""

import errno
import fnmatch
import json
import logging
import os
import shutil
from pathlib import Path

import pytest

from eligsir_o3d import Config
from eligsir_o3d.io.atomic import WriteFailed, atomic_write, atomic_write_text, write_failed
from eligsir_o3d.io.checkpoint import read_checkpoint
from eligsir_o3d.run.pipeline import MappingPipeline, RunOptions, run_mapping

ENOSPC = f"[Errno {errno.ENOSPC} ENOSPC] {os.strerror(errno.ENOSPC)}"


@pytest.fixture
def disk_full(monkeypatch):
    """``disk_full(pattern, calls=None)``: the disk is full for files whose path matches the fnmatch ``pattern``
    (for the ``calls``-th writes of such files only, counted from 1, when given)."""
    real_fsync, rules = os.fsync, []

    def fsync(fd):
        tmp = Path(os.readlink(f"/proc/self/fd/{fd}"))
        if tmp.name.startswith(".") and tmp.name.endswith(".tmp"):  # atomic_write's .NAME.PID.tmp
            target = str(tmp.with_name(tmp.name[1:].rsplit(".", 2)[0]))
            for rule in rules:
                if fnmatch.fnmatch(target, rule["pattern"]):
                    rule["seen"] += 1
                    if rule["calls"] is None or rule["seen"] in rule["calls"]:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return lambda pattern, calls=None: rules.append({"pattern": pattern, "calls": calls, "seen": 0})


def test_atomic_write_keeps_the_old_file_and_names_the_file_and_the_os_error(tmp_path, disk_full):
    path = atomic_write_text(tmp_path / "metrics.json", '{"old": 1}')
    disk_full("*/metrics.json")
    with pytest.raises(WriteFailed) as e:
        atomic_write_text(path, '{"new": 2}')
    assert str(e.value) == f"cannot write {path}: {ENOSPC}" and e.value.errno == errno.ENOSPC
    assert json.loads(path.read_text()) == {"old": 1} and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]

    def torch_like(f):  # torch.save wraps the OSError of a failed write in a RuntimeError
        try:
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        except OSError:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598") from None

    with pytest.raises(WriteFailed, match=rf"cannot write .*x\.pt: \[Errno {errno.EIO} EIO\]"):
        atomic_write(tmp_path / "x.pt", torch_like)
    assert not (tmp_path / "x.pt").exists() and str(write_failed("a", ValueError("bad\nmore"))) == \
        "cannot write a: ValueError: bad"


def _cfg():
    cfg = Config(renderer="torch")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 4
    return cfg


def test_failed_periodic_checkpoint_keeps_mapping_keeps_the_previous_one_and_retries(tmp_path, disk_full, caplog,
                                                                                      monkeypatch):
    ck = tmp_path / "checkpoint.pt"
    disk_full(str(ck), calls={2, 3})  # the checkpoints at source frames 6 and 9 fail, 3 and 12 are written
    after = {}  # next_source -> (checkpoint bytes on disk, its next_source) right after that checkpoint
    orig = MappingPipeline._save_state

    def spy(self, k):
        orig(self, k)
        after[k] = (ck.read_bytes(), read_checkpoint(ck, sequence=self.seq)["extra"]["next_source"])

    monkeypatch.setattr(MappingPipeline, "_save_state", spy)
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        m = run_mapping("synthetic", tmp_path, _cfg(), RunOptions(max_frames=20, holdout_every=4, eval_every=0,
                                                                  checkpoint_every=3, progress=False, plots=False,
                                                                  pictures=False))
    assert sorted(after) == [3, 6, 9, 12]
    # while the disk was full, the checkpoint of frame 3 stayed on disk, unchanged and loadable
    assert after[6] == after[3] and after[9] == after[3] and after[3][1] == 3
    assert after[12][1] == 12  # the retry at the next interval wrote it
    assert m["frames_released"] == 15 and m["frames_admitted"] > 0  # mapping went on to the end
    assert m["checkpoint_failures"] == [{"next_source": 6, "error": f"cannot write {ck}: {ENOSPC}"},
                                        {"next_source": 9, "error": f"cannot write {ck}: {ENOSPC}"}]
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert sum("mapping continues" in w for w in warnings) == 1, warnings  # warned once
    assert any("tried again every 3 source frames" in w for w in warnings)
    assert any("written again at source frame 12" in w for w in warnings)
    assert json.loads((tmp_path / "metrics.json").read_text())["checkpoint_failures"] == m["checkpoint_failures"]


MAP_ARGS = ["map", "synthetic", "--max-frames", "10", "--holdout-every", "5", "--eval-every", "0",
            "--updates-per-frame", "2", "--renderer", "torch", "-q"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished results folder (pictures included): what a second run over it must not destroy."""
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    out = tmp_path_factory.mktemp("full_disk") / "run"
    r = CliRunner().invoke(app, MAP_ARGS + ["--out", str(out)])
    assert r.exit_code == 0, r.output
    return out


def _loads(path: Path) -> None:
    """Raises unless ``path`` is a readable file of its kind."""
    if path.suffix == ".ply":
        from eligsir_o3d.io.ply import load_ply

        assert len(load_ply(path)) > 0
    elif path.suffix == ".json":
        json.loads(path.read_text())
    elif path.suffix == ".png":
        import cv2

        assert cv2.imread(str(path)) is not None


@pytest.mark.parametrize("stage", ["map.ply", "config.json", "heldout/*.png", "metrics.json"])
def test_a_full_disk_at_each_final_output_keeps_the_old_file_writes_the_rest_and_exits_3(tmp_path, finished,
                                                                                         disk_full, stage):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    out = tmp_path / "run"
    shutil.copytree(finished, out)
    failing = sorted(p for p in out.rglob("*") if fnmatch.fnmatch(str(p.relative_to(out)), stage))
    before = {p: p.read_bytes() for p in failing}
    assert failing
    for p in (out / "map.ply", out / "metrics.json"):  # what must be written again despite the failure
        if p not in before:
            p.unlink()
    disk_full(str(out / stage))
    pictures = [] if stage.startswith("heldout") else ["--no-pictures"]  # (faster) the old ones stay as they are
    r = CliRunner().invoke(app, MAP_ARGS + pictures + ["--out", str(out), "--overwrite"])
    assert r.exit_code == 3, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.output, r.output  # one line, no traceback
    assert lines[0].startswith(f"error: cannot write {out / stage.replace('*.png', '')}") and ENOSPC in lines[0]
    first = lines[0].split(":", 2)[1].split("cannot write ")[1]
    assert before.get(Path(first)) is not None, (first, list(before))  # names the file that failed
    for p, data in before.items():  # intact and loadable
        assert p.read_bytes() == data, p
        _loads(p)
    for p in (out / "map.ply", out / "metrics.json", out / "config.json"):
        if p not in before:
            _loads(p)  # written although another file failed
    if stage != "metrics.json":
        metrics = json.loads((out / "metrics.json").read_text())
        assert any(first in f and ENOSPC in f for f in metrics["write_failures"]), metrics["write_failures"]
    assert not list(out.rglob(".*.tmp"))  # no temporary file left behind
    assert not (out / "eligsir.lock").exists()  # the lock is released on this error too


def test_a_flythrough_that_cannot_be_written_whole_keeps_the_old_one(tmp_path, monkeypatch):
    """OpenCV's video writer ignores write errors: the file is fsynced and read back before it replaces the old."""
    import numpy as np

    from eligsir_o3d.visual.video import VideoWriter, _commit_video

    def video(n):
        w = VideoWriter(tmp_path / "flythrough.mp4", 24, codec="mp4v")  # OpenCV's writer: the case it guards
        for k in range(n):
            w.write(np.full((48, 64, 3), 20 * k, np.uint8))
        return w

    path = video(3).close()
    old = path.read_bytes()
    real_fsync = os.fsync

    def fsync(fd):
        name = os.readlink(f"/proc/self/fd/{fd}")
        if ".flythrough.mp4." in name and name.endswith(".tmp.mp4"):  # the temporary beside the video
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(WriteFailed, match=rf"^cannot write {path}: \[Errno {errno.ENOSPC} ENOSPC\]"):
        video(5).close()
    monkeypatch.undo()
    w = video(5)  # the disk filled while OpenCV wrote: a truncated file, no error from OpenCV
    w._writer.release()
    with open(w._tmp, "r+b") as f:
        f.truncate(w._tmp.stat().st_size // 2)
    with pytest.raises(WriteFailed, match=rf"^cannot write {path}: 5 frames written, [0-4] readable"):
        _commit_video(w._tmp, path, 5)
    assert path.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["flythrough.mp4"]
