"""Old import paths of the modules that moved in the layout by concern (issue 27) keep working for one release:
the same module object, after a DeprecationWarning naming the new path; the renamed config classes keep their old
names; config files keep their keys."""

import importlib
import json
import sys
import warnings

import pytest

import eligsir_o3d
from eligsir_o3d._moved import MOVED


def _forget(old: str) -> None:
    """Make the next import of ``eligsir_o3d.<old>`` run the finder again."""
    sys.modules.pop(f"eligsir_o3d.{old}", None)
    parent, _, leaf = f"eligsir_o3d.{old}".rpartition(".")
    importlib.import_module(parent)
    if leaf in vars(sys.modules[parent]) and sys.modules[parent].__dict__[leaf].__name__ != f"{parent}.{leaf}":
        delattr(sys.modules[parent], leaf)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_is_the_new_module_with_a_warning(old):
    _forget(old)
    with pytest.warns(DeprecationWarning, match=f"eligsir_o3d.{old} moved to eligsir_o3d.{MOVED[old]}"):
        mod = importlib.import_module(f"eligsir_o3d.{old}")
    assert mod is importlib.import_module(f"eligsir_o3d.{MOVED[old]}")


def test_from_imports_of_old_paths():
    for name in ("pipeline", "checkpoint", "clock"):
        _forget(name)
    with pytest.warns(DeprecationWarning):
        from eligsir_o3d.pipeline import RunOptions, run_mapping  # noqa: F401
    with pytest.warns(DeprecationWarning):
        from eligsir_o3d.clock import ClockConfig, get_clock  # noqa: F401
    from eligsir_o3d.budget import ClockConfig as new

    assert ClockConfig is new
    with pytest.warns(DeprecationWarning):
        from eligsir_o3d import checkpoint
    assert checkpoint.read_checkpoint is importlib.import_module("eligsir_o3d.io.checkpoint").read_checkpoint


def test_unknown_names_still_fail():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("eligsir_o3d.no_such_module")
    with pytest.raises(AttributeError):
        eligsir_o3d.optim.no_such_loss  # noqa: B018


def test_the_new_paths_do_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        from eligsir_o3d.io.checkpoint import read_checkpoint  # noqa: F401
        from eligsir_o3d.optim import LossConfig  # noqa: F401 (optim was one module in the first release)
        from eligsir_o3d.run.pipeline import run_mapping  # noqa: F401


def test_renamed_config_classes_keep_old_names_and_keys():
    from eligsir_o3d import Config
    from eligsir_o3d.scheduling.fixed_work import FixedWorkConfig, LoadConfig
    from eligsir_o3d.scheduling.keyframes import KeyframesConfig, StrideConfig
    from eligsir_o3d.scheduling.plain import SeedingConfig as plain_seeding
    from eligsir_o3d.scheduling.seeding import SeedingConfig
    from eligsir_o3d.scheduling.support import ProbeConfig, SupportConfig

    assert (LoadConfig, StrideConfig, ProbeConfig, plain_seeding) == (FixedWorkConfig, KeyframesConfig,
                                                                      SupportConfig, SeedingConfig)
    cfg = Config()
    assert (type(cfg.fixed_work), type(cfg.keyframes), type(cfg.support)) == (FixedWorkConfig, KeyframesConfig,
                                                                               SupportConfig)
    keys = set(json.loads(json.dumps(cfg.to_dict())))
    assert {"clock", "fixed_work", "keyframes", "seeding", "support", "views", "fidelity", "growth"} <= keys
    assert Config.from_dict(cfg.to_dict()) == cfg
