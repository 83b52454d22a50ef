"""Outputs only where they belong: a device node is written, never replaced; an input is never an output; a bad
output path is one line with exit 3 (a write failure) or 2 (a refused option), naming the target, never an internal
temporary file. Device nodes are made in the test's own folder (``mknod``: the machine's /dev is never touched)."""

from __future__ import annotations

import os
import stat

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from eligsir_o3d.io.atomic import WriteFailed, atomic_write_text, commit_file, output_kind, temp_for
from helpers.small_runs import write_small_map


@pytest.fixture
def map_ply(tmp_path):
    return write_small_map(tmp_path / "run")


def _node(tmp_path, name: str, minor: int):
    """A character device like /dev/null (minor 3) or /dev/full (minor 7) in the test's folder."""
    p = tmp_path / name
    try:
        os.mknod(p, stat.S_IFCHR | 0o666, os.makedev(1, minor))
    except (PermissionError, OSError) as e:
        pytest.skip(f"cannot make a device node here ({e})")
    return p


def _one_line(r, code):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert r.output.startswith("error: "), r.output


def _still_device(p):
    assert stat.S_ISCHR(os.lstat(p).st_mode), f"{p} was replaced"


@pytest.mark.parametrize("flag", ["--spz", "--splat", "--point-cloud", "--for-viewers"])
def test_export_onto_a_full_device_fails_with_exit_3_and_leaves_the_node(map_ply, tmp_path, flag):
    full = _node(tmp_path, "full", 7)
    (map_ply.parent / "run.json").write_text('{"camera": {"width": 64, "height": 48, "fx": 50, "fy": 50, '
                                             '"cx": 32, "cy": 24}}')
    r = CliRunner().invoke(app, ["export", str(map_ply), flag, str(full)])
    _one_line(r, 3)
    assert "No space left" in r.output and ".tmp" not in r.output and "baked" not in r.output
    _still_device(full)


def test_export_into_a_null_device_is_written_not_replaced(map_ply, tmp_path):
    null = _node(tmp_path, "null", 3)
    r = CliRunner().invoke(app, ["export", str(map_ply), "--point-cloud", str(null)])
    assert r.exit_code == 0, r.output
    _still_device(null)


def test_render_video_onto_a_full_device(map_ply, tmp_path):
    full = _node(tmp_path, "full", 7)
    r = CliRunner().invoke(app, ["render", str(map_ply), "--poses", str(map_ply.parent / "trajectory.txt"),
                                 "--video", str(full), "--scale", "0.1", "--renderer", "torch"])
    _one_line(r, 3)
    _still_device(full)


@pytest.mark.parametrize("flag", ["--spz", "--splat"])
def test_export_web_formats_onto_the_map_are_refused(map_ply, flag):
    before = map_ply.read_bytes()
    r = CliRunner().invoke(app, ["export", str(map_ply), flag, str(map_ply)])
    _one_line(r, 2)
    assert "would overwrite the input" in r.output and map_ply.read_bytes() == before


def test_spz_named_splat_and_suffixless_paths(map_ply, tmp_path):
    r = CliRunner().invoke(app, ["export", str(map_ply), "--spz", str(tmp_path / "x.splat")])
    _one_line(r, 2)
    assert "ends in .splat" in r.output and not (tmp_path / "x.splat").exists()
    r = CliRunner().invoke(app, ["export", str(map_ply), "--point-cloud", str(tmp_path / "cloud")])
    _one_line(r, 2)
    assert "must end in" in r.output
    r = CliRunner().invoke(app, ["export", str(map_ply), "--spz", str(tmp_path / "web")])  # the format is known
    assert r.exit_code == 0, r.output
    assert (tmp_path / "web").read_bytes()[:2] == b"\x1f\x8b" or (tmp_path / "web").stat().st_size > 0


def test_export_into_a_read_only_folder_is_exit_3_naming_the_target(map_ply, tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        r = CliRunner().invoke(app, ["export", str(map_ply), "--spz", str(ro / "x.spz")])
        _one_line(r, 3)
        assert "x.spz" in r.output and ".baked" not in r.output and ".tmp" not in r.output
    finally:
        ro.chmod(0o755)


def test_output_that_is_a_directory_or_below_a_file(map_ply, tmp_path):
    (tmp_path / "d.ply").mkdir()
    r = CliRunner().invoke(app, ["export", str(map_ply), "--point-cloud", str(tmp_path / "d.ply")])
    _one_line(r, 3)
    assert "directory" in r.output
    r = CliRunner().invoke(app, ["export", str(map_ply), "--point-cloud", str(map_ply.parent / "trajectory.txt"
                                                                              / "c.ply")])
    _one_line(r, 3)
    assert "Not a directory" in r.output


def test_atomic_write_and_commit_on_fifo_without_reader(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert output_kind(fifo) == "fifo"
    with pytest.raises(WriteFailed, match="no reader"):
        atomic_write_text(fifo, "x")
    tmp = temp_for(fifo, ".txt")
    assert tmp.parent != tmp_path  # never a temporary beside a node
    tmp.write_text("x")
    with pytest.raises(WriteFailed, match="no reader"):
        commit_file(tmp, fifo)
    assert not tmp.exists() and stat.S_ISFIFO(os.lstat(fifo).st_mode)
    with pytest.raises(WriteFailed, match="is a directory"):
        atomic_write_text(tmp_path, "x")
