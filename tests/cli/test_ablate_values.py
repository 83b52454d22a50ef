"""``--ablate`` values: the mechanism names only (views, fidelity, growth), by the CLI and by the options path behind
``eligsir map``, ``eligsir batch`` and the examples (run.options.to_config); an unknown value is named with the
valid ones."""

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from eligsir_o3d.cli.map_options import ablation
from eligsir_o3d.run.options import MapOptions, to_config


def test_the_options_path_takes_the_mechanism_names():
    assert to_config(MapOptions(ablate=("views", "growth", "views"))).ablate == ("growth", "views")
    with pytest.raises(ValueError, match="scheduling"):
        to_config(MapOptions(ablate=("fidelity", "scheduling"))).resolve()


def test_unknown_values_are_named_with_the_valid_ones(tmp_path):
    assert [ablation(v) for v in ("views", "fidelity", "growth")] == ["views", "fidelity", "growth"]
    with pytest.raises(ValueError, match="'views', 'fidelity', 'growth'"):
        ablation("schedule")
    r = CliRunner().invoke(app, ["map", "synthetic", "--ablate", "schedule", "--out", str(tmp_path / "run")])
    assert r.exit_code == 2 and "'schedule' is not one of" in r.output and "Traceback" not in r.output, r.output
