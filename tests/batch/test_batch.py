"""eligsir batch: manifests, three sequences mapped in parallel on a local Ray, a SIGKILLed worker whose retry
resumes from its checkpoint and ends bit-identical to an uninterrupted run, a corrupt sequence failing alone,
a re-run that maps nothing, and a one-line install hint without Ray."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from eligsir_o3d.batch import BatchError, SequenceSpec, expand_inputs, read_manifest
from eligsir_o3d.batch.specs import Defaults, build_request, folder_status, write_state
from eligsir_o3d.cli.app import app
from helpers.small_runs import start_local_ray

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
SEVEN = DATA / "7scenes_redkitchen_jpg1000"
SUN3D = DATA / "sun3d_mit76_studyroom_f0935"
needs_data = pytest.mark.skipif(not SEVEN.is_dir() or not SUN3D.is_dir(), reason="../shared/data is not available")


# ---- manifests and folder states (no Ray) ---------------------------------------------------------------------
def test_manifest_options_names_and_relative_paths(tmp_path):
    (tmp_path / "rooms").mkdir()
    m = tmp_path / "list.txt"
    m.write_text("# sequences\nrooms/a --max-frames 12 --pose odometry\n\nsynthetic --name room --speed 0.5  # x\n"
                 f"'{tmp_path}/rooms/a' --config fast.json\n")
    specs = expand_inputs([m, "synthetic"])
    names = [s.name for s in specs]
    assert names[1:4:2] == ["room", "synthetic"] and names[0] != names[2]
    assert all(re.fullmatch(r"a-[0-9a-f]{6}", n) for n in (names[0], names[2])), names  # the two "a"s: own suffixes
    assert specs[0].path == str(tmp_path / "rooms" / "a") and specs[0].max_frames == 12 and specs[0].pose == "odometry"
    assert specs[1].path == "synthetic" and specs[1].speed == 0.5
    assert specs[2].config == str(tmp_path / "fast.json")
    # reordering the inputs (issue 31 item 11) keeps every sequence's folder name: nothing finished is remapped
    again = expand_inputs(["synthetic", *reversed(read_manifest(m))])
    assert {(s.path, s.config, s.name) for s in again} == {(s.path, s.config, s.name) for s in specs}
    assert specs[0].where == f"{m}:2"


@pytest.mark.parametrize("line, words", [
    ("synthetic --max-frames ten", ["list.txt:2", "--max-frames", "invalid int"]),
    ("synthetic --frames 3", ["list.txt:2", "unrecognized arguments: --frames 3"]),
    ("'synthetic", ["list.txt:2", "quotation"]),
])
def test_bad_manifest_line_is_one_line_naming_file_and_line(tmp_path, line, words):
    m = tmp_path / "list.txt"
    m.write_text(f"synthetic\n{line}\n")
    with pytest.raises(BatchError) as e:
        read_manifest(m)
    assert "\n" not in str(e.value) and all(w in str(e.value) for w in words), str(e.value)


def test_duplicate_explicit_names_and_empty_manifest(tmp_path):
    m = tmp_path / "list.txt"
    m.write_text("synthetic --name x\nsynthetic --name x\n")
    with pytest.raises(BatchError, match="list.txt:2: the name 'x' is used twice"):
        expand_inputs([m])
    m.write_text("# nothing\n")
    with pytest.raises(BatchError, match="lists no sequences"):
        expand_inputs([m])


def test_folder_states(tmp_path):
    req = build_request(expand_inputs(["synthetic"])[0], Defaults(max_frames=8))
    folder = tmp_path / "synthetic"
    assert folder_status(folder, req) == "new"
    folder.mkdir()
    (folder / "map.ply").write_text("x")
    assert folder_status(folder, req) == "foreign"  # never overwrite what a batch did not write
    write_state(folder, {"request": req, "state": "running"})
    assert folder_status(folder, req) == "resume"
    write_state(folder, {"request": req, "state": "done"})
    assert folder_status(folder, req) == "resume"  # done without metrics.json is not finished
    (folder / "metrics.json").write_text("{}")
    assert folder_status(folder, req) == "done"
    other = dict(req, config=dict(req["config"], device="cuda:0"))
    assert folder_status(folder, other) == "done"  # where it ran is not what was asked for
    assert folder_status(folder, build_request(SequenceSpec("synthetic", name="synthetic"),
                                               Defaults(max_frames=9))) == "changed"


def test_ray_is_imported_only_when_there_is_mapping_to_do():
    import subprocess

    code = "import sys, eligsir_o3d.batch, eligsir_o3d.cli.app; print('ray' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() \
        == "False"


def test_without_ray_the_command_prints_an_install_hint(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    r = CliRunner().invoke(app, ["batch", "synthetic", "--out", str(tmp_path / "b"), "--max-frames", "4"])
    assert r.exit_code == 2, r.output
    assert r.output.strip().splitlines() == ["error: eligsir batch needs Ray: pip install 'eligsir-o3d[batch]' "
                                             "(or: pip install ray)"]
    assert r.exception is None or isinstance(r.exception, SystemExit)


# ---- on a local Ray ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def local_ray():
    ray = start_local_ray()
    yield ray
    ray.shutdown()


def _rows(out: Path) -> dict:
    with open(out / "summary.csv") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


@needs_data
def test_three_sequences_in_parallel_then_a_rerun_maps_nothing(tmp_path, local_ray):
    m = tmp_path / "list.txt"
    m.write_text(f"{SUN3D} --max-frames 16 --name sun3d\n{SEVEN} --max-frames 24 --name kitchen\n"
                 "synthetic --max-frames 16\n")
    out = tmp_path / "batch"
    args = ["batch", str(m), "--out", str(out), "--eval-every", "0", "--no-plots", "--checkpoint-every", "4"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    rows = _rows(out)
    assert list(rows) == ["sun3d", "kitchen", "synthetic"]
    spans = {}
    for name, frames in (("sun3d", 16), ("kitchen", 24), ("synthetic", 16)):
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert metrics["frames_total"] == frames  # the manifest line's own --max-frames
        assert (out / name / "map.ply").is_file() and (out / name / "checkpoint.pt").is_file()
        assert rows[name]["status"] == "done" and abs(float(rows[name]["psnr_db"]) - metrics["heldout"]["psnr"]) < 1e-9
        state = json.loads((out / name / "batch.json").read_text())
        spans[name] = (state["started"], state["finished"])
    # two CPUs, one per task: two of the sequences were mapped at the same time
    pairs = [(a, b) for a in spans for b in spans if a < b]
    assert any(spans[a][0] < spans[b][1] and spans[b][0] < spans[a][1] for a, b in pairs), spans
    assert "PSNR [dB]" in r.output and "3 of 3 sequences finished (0 earlier), 0 failed" in r.output

    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != "summary.csv"}
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0, again.output
    assert "to map on Ray" not in again.output  # no task was started
    assert again.output.count("finished earlier, not mapped again") == 3
    assert "3 of 3 sequences finished (3 earlier), 0 failed" in again.output
    assert r.output.split("\nmetric")[1].split("\n\n")[0] == again.output.split("\nmetric")[1].split("\n\n")[0]
    assert {p: p.stat().st_mtime_ns for p in mtimes} == mtimes
    assert {n: row["status"] for n, row in _rows(out).items()} == dict.fromkeys(rows, "done-earlier")


@needs_data
def test_killed_worker_resumes_from_checkpoint_and_corrupt_sequence_fails_alone(tmp_path, local_ray):
    from eligsir_o3d.batch import map_many

    cfg = tmp_path / "updates.json"  # the fixed-updates budget: a resumed run repeats the uninterrupted one exactly
    cfg.write_text(json.dumps({"clock": {"mode": "updates", "updates_per_frame": 4}}))
    bad = tmp_path / "corrupt"
    bad.mkdir()
    (bad / "rgb.txt").write_text("0.0 rgb/0.png\n0.1 rgb/1.png\n")
    (bad / "depth.txt").write_text("0.0 depth/0.png\nnot-a-time depth/1.png\n")
    m = tmp_path / "list.txt"
    m.write_text(f"{SEVEN} --name killed\n{SEVEN} --name whole\n{bad}\n")
    out = tmp_path / "batch"
    lines, box = [], {}

    def run():
        box["results"] = map_many([m], out, max_frames=24, config=str(cfg), eval_every=0, plots=False,
                                  checkpoint_every=4, max_retries=2, echo=lines.append)

    t = threading.Thread(target=run)
    t.start()
    ck, state = out / "killed" / "checkpoint.pt", out / "killed" / "batch.json"
    deadline = time.time() + 300
    while not ck.is_file() and time.time() < deadline:
        time.sleep(0.05)
    assert ck.is_file(), lines
    pid = json.loads(state.read_text())["pid"]
    os.kill(pid, signal.SIGKILL)  # the worker mapping "killed", after its first checkpoint
    t.join(600)
    assert not t.is_alive()
    res = {r.name: r for r in box["results"]}

    killed, whole, corrupt = res["killed"], res["whole"], res["corrupt"]
    assert killed.status == "done" and killed.attempts == 2 and killed.resumed_from >= 4, (killed, lines)
    assert f"killed: attempt 2 resumes from its checkpoint at source frame {killed.resumed_from}" in "\n".join(lines)
    # the pipeline itself logged that it resumed at that frame (not just our reading of the checkpoint)
    log = (out / "killed" / "batch.log").read_text()
    assert re.search(rf"resum\w* .*\b{killed.resumed_from}\b", log), log
    assert whole.status == "done" and whole.attempts == 1 and whole.resumed_from is None
    assert abs(killed.metrics["heldout"]["psnr"] - whole.metrics["heldout"]["psnr"]) < 0.01
    assert killed.metrics["updates"] == whole.metrics["updates"]
    assert (out / "killed" / "map.ply").read_bytes() == (out / "whole" / "map.ply").read_bytes()  # bit-identical

    assert corrupt.status == "failed" and "\n" not in corrupt.error and "depth.txt:2" in corrupt.error, corrupt.error
    assert f"corrupt: FAILED: {corrupt.error}" in lines
    rows = _rows(out)
    assert rows["corrupt"]["status"] == "failed" and rows["corrupt"]["error"] == corrupt.error
    assert rows["killed"]["attempts"] == "2" and rows["killed"]["resumed_from"] == str(killed.resumed_from)


def test_progress_lines_and_live_redraw(capsys):
    from eligsir_o3d.batch.report import Progress

    lines = []
    p = Progress(["a", "bb"], echo=lines.append)
    p.handle("a", {"event": "resume", "attempt": 2, "resumed_from": 8, "pid": 7, "host": "h", "threads": 1, "t": 0.0})
    for k in (9, 12, 16, 21, 40):
        p.handle("a", {"event": "progress", "frames": k, "total": 40})
    p.handle("bb", {"event": "failed", "error": "x.txt:1: bad"})
    assert lines[0] == "a: attempt 2 resumes from its checkpoint at source frame 8 on h (pid 7, 1 thread(s))"
    assert lines[1].startswith("a: 12/40 frames (30%), ETA ") and lines[1].endswith("attempt 2")  # first quarter
    assert lines[2].startswith("a: 21/40 frames (52%)") and len(lines) == 4  # one line per quarter, not per frame
    assert lines[3] == "bb: FAILED: x.txt:1: bad"
    live = Progress(["a", "bb"], echo=print, live=True)
    live.handle("a", {"event": "start", "attempt": 1, "t": 0.0})
    live.handle("a", {"event": "progress", "frames": 3, "total": 10})
    out = capsys.readouterr().out
    assert "a: attempt 1 maps from frame 0" in out and "\x1b[2F\x1b[J" in out  # the 2-line block redrawn in place
    assert out.split("\x1b[J")[-1].rstrip().splitlines() == ["  a   3/10 frames (30%), ETA " + out.split("ETA ")[-1].split(",")[0]
                                              + ", attempt 1", "  bb  queued"]
