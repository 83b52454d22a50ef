"""A repository script (a benchmark or a tool, run by path rather than imported from a package) loaded as a module,
so that tests can call its functions."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def load_script(relpath: str, name: str | None = None):
    """The module of ``ROOT / relpath`` (named ``name``, default the file's stem), freshly executed."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def synthetic_run(out: Path, updates_per_frame: int, drain_updates: int) -> Path:
    """A results folder of ``eligsir map``'s pipeline on 16 frames of the synthetic room (every 4th held out), at a
    fixed number of updates per frame (the given poses are the map's), for the tests
    of the benchmarks that read results folders."""
    from eligsir_o3d import Config
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", updates_per_frame, drain_updates
    run_mapping("synthetic", out, cfg, RunOptions(max_frames=16, holdout_every=4, eval_every=0, progress=False,
                                                  plots=False, pictures=False))
    return out
