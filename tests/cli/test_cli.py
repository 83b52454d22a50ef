"""The command line as a user reads it: options change what they say they change, bad keys are named with the
nearest valid one, help shows its defaults, --version and 'eligsir config' work. And the config vocabulary."""

import json

import numpy as np
import open3d as o3d
import pytest
from typer.testing import CliRunner

import eligsir_o3d as eo3d
from eligsir_o3d.cli.app import app
from eligsir_o3d.config import Config, apply_override

RUN = ["map", "synthetic", "--max-frames", "10", "--holdout-every", "5", "--eval-every", "0", "--renderer", "torch",
       "-q"]


def _map(tmp_path, name, *extra):
    r = CliRunner().invoke(app, [*RUN, "--out", str(tmp_path / name), *extra])
    assert r.exit_code == 0, r.output
    return (json.loads((tmp_path / name / f).read_text()) for f in ("metrics.json", "config.json"))


def test_updates_per_frame_selects_the_updates_clock_and_sets_the_count(tmp_path):
    (m2, c2), (m3, _) = (_map(tmp_path, f"u{n}", "--updates-per-frame", str(n), "--set", "clock.drain_updates=0")
                         for n in (2, 3))
    assert m2["clock"] == "updates" and c2["clock"]["mode"] == "updates" and c2["clock"]["updates_per_frame"] == 2
    assert (m2["updates"], m3["updates"]) == (2 * m2["frames_source"], 3 * m3["frames_source"])


def test_conflicting_clock_options_are_an_error(tmp_path):
    r = CliRunner().invoke(app, [*RUN, "--clock", "cost", "--updates-per-frame", "2", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "conflicting clock options" in r.output


def test_depth_max_caps_the_measured_depth(tmp_path):
    common = ("--updates-per-frame", "1", "--set", "clock.drain_updates=0")
    (near, c_near), (far, _) = _map(tmp_path, "near", "--depth-max", "1.5", *common), _map(tmp_path, "far", *common)
    assert c_near["depth_max"] == 1.5
    # the room's walls are 2-4 m away: with a 1.5 m range most depth is gone, and so are most seeds
    assert near["gaussians"] < far["gaussians"] / 2 or near["skipped_frames"]


def test_set_changes_a_config_key_and_names_the_nearest_for_a_typo(tmp_path):
    _, cfg = _map(tmp_path, "s", "--updates-per-frame", "1", "--set", "views.active_size=3", "--set",
                  "clock.drain_updates=0")
    assert cfg["views"]["active_size"] == 3
    r = CliRunner().invoke(app, [*RUN, "--set", "views.activ_size=3", "--out", str(tmp_path / "t")])
    assert r.exit_code == 2 and "did you mean 'views.active_size'" in r.output and "Traceback" not in r.output


def test_help_version_and_config_command():
    runner = CliRunner()
    help_text = runner.invoke(app, ["map", "--help"], env={"COLUMNS": "200"}).output
    assert "default: the config's, 8" in help_text  # rich would have eaten a "[default: ...]" as markup
    for panel in ("Input", "Pose", "Budget", "Evaluation", "Output"):
        assert panel in help_text
    version = runner.invoke(app, ["--version"])
    assert version.exit_code == 0 and eo3d.__version__ in version.output
    printed = runner.invoke(app, ["config", "--set", "seed=7"])
    assert printed.exit_code == 0
    data = json.loads(printed.output)
    assert data["seed"] == 7 and Config.from_dict(data).clock.mode == "cost"


def test_config_files_reject_unknown_keys(tmp_path):
    with pytest.raises(ValueError, match=r"x\.json: unknown key 'growth\.min_view'; did you mean 'growth\.min_views'"):
        Config.from_dict({"growth": {"min_view": 3}}, "x.json")
    with pytest.raises(ValueError, match=r"unknown key 'optim\.updates_per_frame'"):
        Config.from_dict({"optim": {"updates_per_frame": 5}})
    with pytest.raises(ValueError, match=r"unknown key 'fixed_scale'"):
        Config.from_dict({"fixed_scale": 0.5})
    cfg = Config.from_dict({"clock": {"mode": "updates", "updates_per_frame": 5}, "fidelity": {"fixed_scale": 0.5}})
    assert (cfg.clock.updates_per_frame, cfg.clock.mode, cfg.fidelity.fixed_scale) == (5, "updates", 0.5)
    cfg = Config()
    with pytest.raises(ValueError, match="takes a int"):
        apply_override(cfg, "seed=abc")
    apply_override(cfg, "fidelity.scales=[0.5, 1.0]")
    assert cfg.fidelity.scales == (0.5, 1.0)


def test_resolve_computes_derived_values_on_a_copy():
    cfg = Config(device="CUDA:0", renderer="auto")
    r = cfg.resolve()
    assert r.device == "cuda:0" and r.renderer in ("gsplat", "torch") and cfg.device == "CUDA:0"
    assert Config(device="CPU").resolve().device == "cpu" and r.resolve().to_dict() == r.to_dict()
    with pytest.raises(ValueError, match="not a device name"):
        Config(device="gpu0").resolve()


def test_reconstructor_takes_the_depth_scale():
    W, H = 32, 24
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, 30.0, 30.0, (W - 1) / 2, (H - 1) / 2)
    color = np.full((H, W, 3), 128, np.uint8)
    depth = np.full((H, W), 5000, np.uint16)  # 1 m at a TUM-style depth scale of 5000
    rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(depth))
    rec = eo3d.Reconstructor(intr, "cpu", depth_scale=5000.0)
    rec.integrate(rgbd, np.eye(4), updates=0)
    assert rec.config.depth_scale == 5000.0
    assert float(rec.views.views[0].depth.max()) == pytest.approx(1.0)


def test_setting_a_config_attribute_that_does_not_exist_fails_loudly():
    """A misspelt setting, or one in the wrong section, assigned in Python is not silently ignored."""
    from eligsir_o3d import Config

    cfg = Config()
    with pytest.raises(AttributeError, match=r"OptimConfig has no setting 'updates_per_frame'"):
        cfg.optim.updates_per_frame = 4
    with pytest.raises(AttributeError, match=r"did you mean 'seed_stride'"):
        cfg.growth.seed_strid = 1
    with pytest.raises(AttributeError, match=r"did you mean 'sh_degree'"):
        cfg.sh_degre = 1
    cfg.clock.updates_per_frame = 4  # a real setting still assigns
    assert cfg.resolve().clock.updates_per_frame == 4
