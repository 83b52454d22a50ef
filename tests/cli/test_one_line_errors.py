"""Issue 31 items 4 and 8: a command never overwrites its own input, and bad numbers or corrupt files give one
line and exit 2 instead of a traceback (eval on a corrupt metrics.json, calibrate-color --stride 0 / --pairs 0,
render --scale 200, export --mesh --voxel-size 0.0001)."""

import json
import os

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from helpers.small_runs import write_small_map


@pytest.fixture
def map_ply(tmp_path):
    return write_small_map(tmp_path / "run")


def _one_line_error(r, code=2):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert r.output.startswith("error: "), r.output


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "relative"])
def test_export_refuses_to_overwrite_the_map(map_ply, how, monkeypatch):
    before = map_ply.read_bytes()
    target = map_ply
    if how == "symlink":
        target = map_ply.parent / "link.ply"
        target.symlink_to(map_ply)
    elif how == "hardlink":
        target = map_ply.parent / "hard.ply"
        os.link(map_ply, target)
    elif how == "relative":
        monkeypatch.chdir(map_ply.parent)
        target = "./../run/map.ply"
    r = CliRunner().invoke(app, ["export", str(map_ply), "--point-cloud", str(target)])
    _one_line_error(r)
    assert "would overwrite the input" in r.output
    assert map_ply.read_bytes() == before


def test_export_refuses_mesh_over_the_trajectory_and_one_path_twice(map_ply, tmp_path):
    traj = map_ply.parent / "trajectory.txt"
    r = CliRunner().invoke(app, ["export", str(map_ply), "--mesh", str(traj)])
    _one_line_error(r)
    r = CliRunner().invoke(app, ["export", str(map_ply), "--mesh", str(tmp_path / "a.ply"), "--point-cloud",
                                 str(tmp_path / "a.ply")])
    _one_line_error(r)
    assert "given as both" in r.output


def test_export_mesh_with_a_tiny_voxel_is_refused_up_front(map_ply, tmp_path):
    r = CliRunner().invoke(app, ["export", str(map_ply), "--mesh", str(tmp_path / "m.ply"), "--voxel-size", "0.0001"])
    _one_line_error(r)
    assert "GiB" in r.output and "--voxel-size" in r.output and not (tmp_path / "m.ply").exists()


def test_render_with_a_huge_scale_is_refused(map_ply, tmp_path):
    r = CliRunner().invoke(app, ["render", str(map_ply), "--poses", str(map_ply.parent / "trajectory.txt"),
                                 "--out", str(tmp_path / "frames"), "--scale", "200"])
    _one_line_error(r)
    assert "MPix" in r.output


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", "\xff\xfe"])
def test_eval_on_a_corrupt_metrics_json(tmp_path, text):
    (tmp_path / "metrics.json").write_bytes(text.encode("latin-1"))
    r = CliRunner().invoke(app, ["eval", str(tmp_path)])
    _one_line_error(r)
    assert "metrics.json: not a valid metrics.json" in r.output


@pytest.mark.parametrize("opt", [["--stride", "0"], ["--pairs", "0"], ["--stride", "-3"], ["--gap", "0"]])
def test_calibrate_color_bad_numbers(opt):
    r = CliRunner().invoke(app, ["calibrate-color", "synthetic", *opt])
    _one_line_error(r)
    assert opt[0] in r.output
