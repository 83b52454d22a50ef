"""One path from options to a run (issue 27): eligsir map, eligsir batch and the demo build their Config and
RunOptions in eligsir_o3d.run.options, and the cost-model rule is the documented one."""

import pytest
from typer.testing import CliRunner

from eligsir_o3d import Config
from eligsir_o3d.batch.specs import Defaults, SequenceSpec, build_request
from eligsir_o3d.cli import app
from eligsir_o3d.cli.map_options import PANELS, map_options
from eligsir_o3d.run.options import COST_MODEL_RULE, MapOptions, resolve, to_config


def _cli_kwargs(**given):
    """The keyword arguments typer passes to map_cmd: every table default, then ``given``."""
    import inspect

    from eligsir_o3d.cli.app import map_cmd

    kw = {name: p.default.default for name, p in inspect.signature(map_cmd).parameters.items()}
    kw.update(given)
    return kw


def test_map_options_become_config_fields():
    cfg, opts = resolve(MapOptions(seed=3, depth_max=4.5, updates_per_frame=5, speed=0.5, ablate=("views",),
                                   on_bad_frame="stop", offline_updates=77, overrides=["views.active_size=16"],
                                   max_frames=9, holdout_every=4, eval_every=0, pictures=False))
    assert (cfg.seed, cfg.depth_max, cfg.ablate, cfg.views.active_size) == (3, 4.5, ("views",), 16)
    assert (cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.speed) == ("updates", 5, 0.5)
    assert (cfg.clock.on_bad_frame, cfg.clock.offline_updates) == ("stop", 77)
    assert (opts.max_frames, opts.holdout_every, opts.eval_every, opts.pictures) == (9, 4, 0, False)


def test_conflicting_clock_options_are_refused():
    with pytest.raises(ValueError, match="conflicting clock options: realtime, updates"):
        to_config(MapOptions(realtime=True, updates_per_frame=3))


def test_cost_model_rule():
    shipped = Config().clock.cost
    assert to_config(MapOptions()).clock.cost_source == "config"  # the Python API: the config's (shipped)
    assert to_config(MapOptions(cost_model="calibrate")).clock.cost_source == "calibrate"
    assert to_config(MapOptions(cost_model="shipped")).clock.cost == shipped
    assert map_options(_cli_kwargs()).cost_model == "calibrate"  # eligsir map without --cost-model
    assert map_options(_cli_kwargs(cost_model="shipped")).cost_model == "shipped"
    for cmd in ("map", "batch"):
        out = CliRunner().invoke(app, [cmd, "--help"], env={"COLUMNS": "400"}).output
        assert "'eligsir batch'" in out and "shipped" in out, cmd
    assert "same budget" in COST_MODEL_RULE


@pytest.mark.parametrize("cost_model", [None, "shipped", "calibrate"])
def test_batch_and_map_build_the_same_config(cost_model):
    """The same options give the same Config on both entry points (the cost model by the rule)."""
    spec = SequenceSpec(path="synthetic", name="s", seed=2, speed=0.5, updates_per_frame=4, cost_model=cost_model)
    request = build_request(spec, Defaults())
    mapped = to_config(MapOptions(seed=2, speed=0.5, updates_per_frame=4, cost_model=cost_model))
    assert request["config"] == mapped.to_dict()


def test_every_option_of_the_table_reaches_map_options_or_is_cli_only():
    from dataclasses import fields

    from eligsir_o3d.cli.map_options import CLI_ONLY

    names = {name for panel in PANELS for name, _, _ in panel}
    assert names - set(CLI_ONLY) <= {f.name for f in fields(MapOptions)}
