"""Every config key states its rule and unit in a one-line attribute docstring under its field; ``eligsir config
--explain KEY`` prints it with the key's type and default; the docs' generated reference pages (CLI and config) are
what the code says today."""

import dataclasses

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli import app
from eligsir_o3d.cli.config_explain import explain, key_docs
from eligsir_o3d.cli.reference import pages
from eligsir_o3d.config import Config
from helpers import ROOT

def test_every_config_key_has_a_one_line_docstring():
    docs = key_docs()
    assert len(docs) > 140 and {"device", "clock.cost.update_s", "growth.mcmc.n_max"} <= {d.key for d in docs}
    missing = [d.key for d in docs if not d.doc]
    assert not missing, f"config keys without an attribute docstring: {missing}"
    multi = [d.key for d in docs if "\n" in d.doc]
    assert not multi, f"docstrings longer than one line: {multi}"


def test_explain_reads_type_default_and_docstring_from_source():
    text = explain("support.scale")
    assert "type:    float" in text and "default: 0.25" in text and "support check" in text
    assert explain("clock.cost").startswith("clock.cost (section CostModel)")
    field = next(f for f in dataclasses.fields(Config) if f.name == "depth_max")
    assert f"default: {field.default!r}" in explain("depth_max")


def test_eligsir_config_explain_and_an_unknown_key():
    runner = CliRunner()
    done = runner.invoke(app, ["config", "--explain", "fidelity.idle_floor_scale"])
    assert done.exit_code == 0 and "default: 0.25" in done.output and "only load" in done.output
    bad = runner.invoke(app, ["config", "--explain", "fidelty.idle_flor_scale"])
    assert bad.exit_code == 2 and "no such config key" in bad.output and "fidelity.idle_floor_scale" in bad.output
    with pytest.raises(ValueError, match="close matches: .*views.fresh_updates"):
        explain("fresh_update")


@pytest.mark.parametrize("rel", ["reference/cli.md", "reference/config.md"])
def test_the_generated_reference_pages_are_current(rel):
    committed = (ROOT / "docs" / rel).read_text()
    assert committed == pages()[rel], (f"docs/{rel} is stale: run "
                                       "`python -m eligsir_o3d.cli.reference docs` and commit the result")


def test_the_config_page_lists_every_key_with_its_rule():
    page = (ROOT / "docs" / "reference" / "config.md").read_text().replace("\\|", "|")
    for d in key_docs():
        if not d.section:
            assert f"| `{d.key}` |" in page, d.key
            if d.doc:
                assert " ".join(d.doc.replace("``", "`").split())[:40] in page, d.key


def test_the_cli_page_lists_every_command_and_option():
    import typer

    page = (ROOT / "docs" / "reference" / "cli.md").read_text()
    group = typer.main.get_command(app)
    assert {"live", "calibrate", "calibrate-color", "batch"} <= set(group.commands)
    for name, cmd in group.commands.items():
        assert f"## eligsir {name}\n" in page, name
        for param in cmd.params:
            for opt in getattr(param, "opts", []):
                if opt.startswith("--") and not getattr(param, "hidden", False):
                    assert opt in page, (name, opt)
