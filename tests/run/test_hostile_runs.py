"""Runs under hostile options and folders: a value no run can use is one line naming the option (the same for map
and batch), an optional output that cannot be written costs that file only, ``--overwrite`` removes only what the
earlier run wrote, ``--resume`` with the same command line continues, endless files are refused unread."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from eligsir_o3d.run.option_table import MAX_MODELLED_S, check_option, default
from eligsir_o3d.run.options import MapOptions, resolve
from eligsir_o3d.run.pipeline import RunOptions, run_mapping
from helpers.small_runs import quick_config, quick_options

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
SMALL = ["--max-frames", "10", "--holdout-every", "5", "--eval-every", "0", "--updates-per-frame", "2",
         "--renderer", "torch", "-q", "--no-pictures"]


_cfg, _opts = quick_config, quick_options


def _one_line(r, code=2):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert r.output.startswith("error: "), r.output
    return r.output


@pytest.mark.parametrize("args, said", [
    (["--max-frames", "-5"], "--max-frames -5: must be an integer >= 1"),
    (["--eval-every", "-5"], "--eval-every -5: must be an integer >= 0"),
    (["--checkpoint-every", "-3"], "--checkpoint-every -3: must be an integer >= 0"),
    (["--speed", "1e-300"], "--speed 1e-300: must be a number >= 1e-06"),
    (["--speed", "nan"], "--speed nan"),
    (["--holdout-every", "-1"], "--holdout-every -1"),
    (["--set", "seed=1180591620717411303424"], "config key seed"),
    (["--set", "clock.speed=1e-300"], "config key clock.speed"),
])
def test_map_refuses_values_no_run_can_use(tmp_path, args, said):
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), *SMALL, *args])
    assert said in _one_line(r), r.output
    assert not (tmp_path / "o" / "map.ply").exists()


def test_map_and_batch_share_defaults_and_checks():
    from eligsir_o3d.batch.specs import Defaults
    from eligsir_o3d.cli.map_options import EVAL_OPTIONS, OUTPUT_OPTIONS

    table = {name: d.default for name, _, d in EVAL_OPTIONS + OUTPUT_OPTIONS}
    for name in ("checkpoint_every", "eval_every", "holdout_every"):
        assert table[name] == default(name) == getattr(Defaults(), name) == getattr(RunOptions(), name) \
            == getattr(MapOptions(), name)
    import inspect

    from eligsir_o3d.batch.runner import map_many

    sig = inspect.signature(map_many).parameters
    assert sig["checkpoint_every"].default == default("checkpoint_every")
    with pytest.raises(ValueError, match="--cpus-per-task 0"):
        check_option("cpus_per_task", 0)
    with pytest.raises(ValueError, match="--eval-every"):
        run_mapping("synthetic", "unused", _cfg(), _opts(eval_every=-5))


def test_speed_floor_follows_the_recordings_length(tmp_path):
    if not SEVEN.is_dir():
        pytest.skip("../shared/data is not available")
    cfg, opts = resolve(MapOptions(speed=2e-6, cost_model="shipped", max_frames=1000))
    with pytest.raises(ValueError) as e:
        run_mapping(str(SEVEN), tmp_path / "o", cfg, opts)
    msg = str(e.value)
    assert msg.startswith("--speed 2e-06:") and "slowest speed" in msg and "\n" not in msg
    assert f"{MAX_MODELLED_S / 86400:.0f} days" in msg


@pytest.mark.parametrize("option", ["--config", "--cost-model", "--holdout-list"])
@pytest.mark.parametrize("node", ["/dev/zero", "fifo", "dir"])
def test_endless_or_odd_files_for_path_options(tmp_path, option, node):
    path = node
    if node == "fifo":
        path = str(tmp_path / "fifo")
        os.mkfifo(path)
    elif node == "dir":
        path = str(tmp_path)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), *SMALL, option, path])
    msg = _one_line(r)
    assert "not a regular file" in msg and path in msg


@pytest.mark.parametrize("content", ['{"no_such_key": 1}', None])
def test_live_config_unknown_key_or_directory(tmp_path, content):
    cfg = tmp_path / "c.json"
    if content is None:
        cfg.mkdir()
    else:
        cfg.write_text(content)
    r = CliRunner().invoke(app, ["live", "--replay", "synthetic", "--frames", "2", "--config", str(cfg),
                                 "--out", str(tmp_path / "o")])
    msg = _one_line(r)
    assert ("no_such_key" in msg) if content else ("directory" in msg)


def test_optional_map_format_out_of_reach_costs_that_file_only(tmp_path, monkeypatch, caplog):
    import eligsir_o3d.export.web as splats

    monkeypatch.setattr(splats, "SPZ_REACH_M", 1e-3)  # as a map 2 km from the origin
    out = tmp_path / "o"
    m = run_mapping("synthetic", out, _cfg(), _opts(formats="ply,spz,splat"))
    for name in ("map.ply", "metrics.json", "run.json", "config.json", "trajectory.txt", "map.splat"):
        assert (out / name).is_file(), name
    assert not (out / "map.spz").exists()
    assert m["write_failures"] == [] and len(m["outputs_skipped"]) == 1 and "map.spz" in m["outputs_skipped"][0]
    assert "SPZ positions reach" in caplog.text


@pytest.fixture(scope="module")
def pictured(tmp_path_factory):
    out = tmp_path_factory.mktemp("pictured") / "run"
    run_mapping("synthetic", out, _cfg(), _opts(pictures=True))
    return out


def test_overwrite_leaves_a_users_own_files_in_heldout(tmp_path, pictured):
    out = tmp_path / "run"
    shutil.copytree(pictured, out)
    ours = sorted(p.name for p in (out / "heldout").iterdir())
    assert ours
    for name in ("notes.png", "123456.png", "mine.json"):
        (out / "heldout" / name).write_text("the user's")
    run_mapping("synthetic", out, _cfg(), _opts(pictures=False, overwrite=True))
    left = sorted(p.name for p in (out / "heldout").iterdir())
    assert left == ["123456.png", "mine.json", "notes.png"], left


def test_eval_deep_metrics_and_unwritable_spatial_out(tmp_path, pictured):
    deep = tmp_path / "deep"
    deep.mkdir()
    (deep / "metrics.json").write_text("[" * 50_000 + "]" * 50_000)
    r = CliRunner().invoke(app, ["eval", str(deep)])
    assert "nested too deeply" in _one_line(r)
    b = tmp_path / "b"
    shutil.copytree(pictured, b)
    blocker = tmp_path / "a-file"
    blocker.write_text("mine")
    r = CliRunner().invoke(app, ["eval", str(pictured), str(b), "--spatial-out", str(blocker)])
    assert r.exit_code == 3 and "Traceback" not in r.output, r.output
    assert "error: " in r.output and "names a file, not a folder" in r.output
    assert blocker.read_text() == "mine"


def test_resume_with_the_same_command_line_under_calibration(tmp_path):
    """The calibration sets clock.cost_feedback itself; resume compares only what the user chose."""
    out = tmp_path / "o"
    args = ["map", "synthetic", "--out", str(out), "--max-frames", "12", "--holdout-every", "6", "--eval-every",
            "0", "--renderer", "torch", "-q", "--no-pictures", "--checkpoint-every", "4", "--speed", "0.02"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert (out / "checkpoint.pt").is_file()
    assert json.loads((out / "config.json").read_text())["clock"]["cost_feedback"] > 0
    r = CliRunner().invoke(app, [*args, "--resume"])
    assert r.exit_code == 0, r.output
    assert "was made with" not in r.output


def test_view_host_spellings_of_every_interface_warn(capsys):
    from eligsir_o3d.cli.commands import show_urls
    from eligsir_o3d.visual.bind_check import is_wildcard, served_urls

    for host in ("0", "::0", "0.0.0.0", "::", "0x0"):
        assert is_wildcard(host), host
        assert served_urls(host, 8080)[0] == "http://127.0.0.1:8080"
    for host in ("127.0.0.1", "::1", "localhost"):
        assert not is_wildcard(host)

    class V:
        urls = served_urls("0", 8080)

    show_urls(V(), "0", "viewer")
    got = capsys.readouterr()
    assert "http://0:" not in got.out and "serves the map to every network" in got.err
