"""Issue 31 items 9 and 11 (config values): a value no run can use is refused with one line naming the key,
however it is given (--set, --depth-max, a config file), before the results folder is touched."""

import json

import pytest
from typer.testing import CliRunner

from eligsir_o3d import Config
from eligsir_o3d.cli.app import app
from eligsir_o3d.config import apply_override


@pytest.mark.parametrize("item, said", [("max_gaussians=-5", "max_gaussians"), ("max_gaussians=0", "max_gaussians"),
                                        ("background=[1,2]", "background"), ("background=[0,0,7]", "background"),
                                        ("depth_max=0", "depth_max"), ("views.active_size=-1", "views.active_size"),
                                        ("sh_degree=9", "sh_degree")])
def test_unusable_set_values_are_refused_naming_the_key(tmp_path, item, said):
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), "--set", item, "-q"])
    assert r.exit_code == 2 and f"config key {said}" in r.output and "Traceback" not in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-1"])
def test_depth_max_option_is_checked_like_set(tmp_path, value):
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), "--depth-max", value, "-q"])
    assert r.exit_code == 2 and "--depth-max" in r.output and "Traceback" not in r.output, r.output
    assert not (tmp_path / "o").exists()


def test_a_config_file_with_nan_is_refused(tmp_path):
    cfg = Config().to_dict()
    cfg["optim"]["lrs"]["means"] = float("nan")
    (tmp_path / "c.json").write_text(json.dumps(cfg))  # json writes a bare NaN
    with pytest.raises(ValueError, match="optim.lrs.means"):
        Config.load(tmp_path / "c.json").resolve()


def test_the_defaults_and_ordinary_values_pass():
    cfg = Config()
    apply_override(cfg, "background=[1,1,1]")
    apply_override(cfg, "seed=3")
    cfg.resolve()
    apply_override(cfg, "seed=-3")
    with pytest.raises(ValueError, match="seed"):
        cfg.resolve()
