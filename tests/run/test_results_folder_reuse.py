"""Issue 31 items 2 and 3: a results folder never mixes or silently loses two runs. A used --out is refused unless
--overwrite (which clears what the new run will not rewrite); --resume where there is no checkpoint to continue is
refused; eligsir map without --out takes a fresh folder name."""

import json

import pytest
from typer.testing import CliRunner

from eligsir_o3d import Config
from eligsir_o3d.cli.app import app
from eligsir_o3d.run.folder_guard import FolderInUse, check_folder, fresh_folder
from eligsir_o3d.run.pipeline import RunOptions, run_mapping

MAP = ["--max-frames", "8", "--holdout-every", "4", "--updates-per-frame", "1", "--eval-every", "0",
       "--renderer", "torch", "-q"]


def _finished(folder, pictures=True):
    """A finished run's files, as eligsir map leaves them (the guard only looks at names)."""
    (folder / "heldout").mkdir(parents=True)
    for name in ("metrics.json", "map.ply", "run.json", "config.json", "trajectory.txt"):
        (folder / name).write_text("{}")
    if pictures:
        (folder / "heldout" / "000002.png").write_bytes(b"old")
        (folder / "flythrough.mp4").write_bytes(b"old")
    (folder / "notes.txt").write_text("mine")  # not eligsir's: never removed


def test_a_used_out_is_refused_without_overwrite(tmp_path):
    _finished(tmp_path)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path), *MAP])
    assert r.exit_code == 2 and "already holds the results of another run" in r.output, r.output
    assert "--overwrite" in r.output and "Traceback" not in r.output
    assert (tmp_path / "flythrough.mp4").read_bytes() == b"old" and (tmp_path / "map.ply").read_text() == "{}"


def test_overwrite_clears_what_the_new_run_does_not_rewrite(tmp_path):
    _finished(tmp_path)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path), "--overwrite", "--no-pictures", *MAP])
    assert r.exit_code == 0, r.output
    assert not (tmp_path / "flythrough.mp4").exists() and not (tmp_path / "heldout").exists()
    assert json.loads((tmp_path / "metrics.json").read_text())["gaussians"] > 0
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_resume_without_a_checkpoint_is_refused_and_changes_nothing(tmp_path):
    _finished(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path), "--resume", *MAP])
    assert r.exit_code == 2 and "--resume" in r.output and "no checkpoint.pt" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


def test_the_api_refuses_too_and_a_new_or_empty_folder_is_fine(tmp_path):
    check_folder(tmp_path / "new", resume=False, overwrite=False)
    check_folder(tmp_path, resume=True, overwrite=False)  # empty: a batch retry before its first checkpoint
    _finished(tmp_path / "x")
    with pytest.raises(FolderInUse):
        run_mapping("synthetic", tmp_path / "x", Config(), RunOptions(max_frames=6, progress=False))


def test_the_default_out_is_a_fresh_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert fresh_folder("runs/map").as_posix() == "runs/map"
    _finished(tmp_path / "runs" / "map")
    (tmp_path / "runs" / "map-2").mkdir()  # empty: free
    assert fresh_folder("runs/map").as_posix() == "runs/map-2"
    (tmp_path / "runs" / "map-2" / "x").write_text("")
    assert fresh_folder("runs/map").as_posix() == "runs/map-3"
    r = CliRunner().invoke(app, ["map", "synthetic", *MAP, "--no-pictures"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "runs" / "map-3" / "metrics.json").is_file()
    assert (tmp_path / "runs" / "map" / "map.ply").read_text() == "{}"
