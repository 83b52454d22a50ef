"""``--ablate`` values: the first release's spelling (``scheduling``, now ``views``) is refused outright with one
line naming the new one, by the CLI and by the options path behind ``eligsir map``, ``eligsir batch`` and the
examples (run.options.to_config); an unknown value is named with the valid ones."""

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from eligsir_o3d.cli.map_options import ablation
from eligsir_o3d.run.options import MapOptions, to_config


def test_first_release_spelling_is_refused_with_one_line(tmp_path):
    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["map", "synthetic", "--max-frames", "4", "--ablate", "scheduling", "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert r.output.startswith("error: --ablate scheduling") and "use --ablate views" in r.output, r.output
    assert not out.exists()  # refused before anything was mapped or written


def test_the_options_path_refuses_it_without_an_alias():
    with pytest.raises(ValueError, match="use --ablate views"):
        to_config(MapOptions(ablate=("fidelity", "scheduling")))
    assert to_config(MapOptions(ablate=("views", "growth", "views"))).ablate == ("growth", "views")


def test_unknown_values_are_named_with_the_valid_ones(tmp_path):
    assert [ablation(v) for v in ("views", "fidelity", "growth")] == ["views", "fidelity", "growth"]
    with pytest.raises(ValueError, match="'views', 'fidelity', 'growth'"):
        ablation("schedule")
    r = CliRunner().invoke(app, ["map", "synthetic", "--ablate", "schedule", "--out", str(tmp_path / "run")])
    assert r.exit_code == 2 and "'schedule' is not one of" in r.output and "Traceback" not in r.output, r.output
