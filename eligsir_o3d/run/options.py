"""One path from a user's options to a run: :class:`MapOptions` (the vocabulary of ``eligsir map``, ``eligsir
batch`` manifests and the examples) -> :func:`to_config` / :func:`to_run_options` -> (:class:`Config`,
:class:`RunOptions`). Every entry point builds its run here, so the same options give the same budget.

Which cost model prices the budget (``--clock cost``) is decided by one rule, :data:`COST_MODEL_RULE`, printed by
``eligsir map --help`` and ``eligsir batch --help``. Light to import (the CLI's help reads it): the config and the
pipeline are imported inside the functions."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

COST_MODELS = ("calibrate", "shipped")  # or the path of a JSON file of terms

COST_MODEL_RULE = ("Cost model (what --clock cost charges an update): --cost-model calibrate fits this machine, "
                   "device and renderer once (cached); shipped is the reference machine's fit, the same budget on "
                   "every machine; FILE is a JSON file of terms. Without --cost-model, 'eligsir map' calibrates "
                   "(unless --config is given: then the file's), while 'eligsir batch', 'eligsir demo', run_mapping "
                   "and Reconstructor use the config's (shipped by default), so a batch spread over machines gets "
                   "one budget. Give the same --cost-model to both to get the same budget.")


@dataclass
class MapOptions:
    """A run as a user asks for it; ``None`` means "the config's" (or the RunOptions default)."""

    # input
    max_frames: int | None = None
    depth_max: float | None = None  # metres
    on_bad_frame: str | None = None  # skip | stop
    config: str | None = None  # a config.json to start from
    overrides: list = field(default_factory=list)  # "KEY=VALUE" items, as --set
    sequence_options: dict | None = None  # open_sequence options (bag topics, register=False, n_frames)
    # pose
    pose: str = "gt"
    # budget
    clock: str | None = None  # cost | updates | realtime
    realtime: bool = False  # same as clock="realtime"
    updates_per_frame: int | None = None  # selects the updates clock
    speed: float | None = None
    cost_model: str | None = None  # calibrate | shipped | FILE | None: see COST_MODEL_RULE
    refine: int = 0
    offline_reference: bool = False
    offline_updates: int = 0
    # evaluation
    holdout_every: int = 8
    holdout_list: str | None = None
    eval_every: int = 100
    # mapper
    device: str | None = None
    renderer: str | None = None
    ablate: tuple = ()
    seed: int | None = None
    # output
    checkpoint_every: int = 0
    resume: bool = False
    force_unlock: bool = False
    progress: bool = True
    plots: bool = True
    pictures: bool = True
    formats: str = "ply"  # map files: "ply", "spz", "splat", comma-separated (map.ply always)


def clock_mode(clock: str | None, realtime: bool, updates_per_frame: int | None) -> str | None:
    """The clock mode the options ask for (None: the config's); contradicting options are an error."""
    asked = {c for c in (clock, "realtime" if realtime else None,
                         "updates" if updates_per_frame is not None else None) if c}
    if len(asked) > 1:
        raise ValueError(f"conflicting clock options: {', '.join(sorted(asked))} (--updates-per-frame selects "
                         "--clock updates, --realtime is --clock realtime)")
    return asked.pop() if asked else None


def to_config(o: MapOptions):
    """The :class:`~eligsir_o3d.Config` of a run: the config file (or the defaults), then ``overrides``, then each
    option given."""
    from ..budget import CostModel
    from ..config import Config, apply_override

    cfg = Config.load(o.config) if o.config else Config()
    for item in o.overrides:
        apply_override(cfg, item)
    for name in ("device", "renderer", "seed", "depth_max"):
        if getattr(o, name) is not None:
            setattr(cfg, name, getattr(o, name))
    if o.ablate:
        cfg.ablate = tuple(sorted(set(o.ablate)))
    mode = clock_mode(o.clock, o.realtime, o.updates_per_frame)
    if mode is not None:
        cfg.clock.mode = mode
    for name in ("updates_per_frame", "speed", "on_bad_frame"):
        if getattr(o, name) is not None:
            setattr(cfg.clock, name, getattr(o, name))
    if o.offline_updates:
        cfg.clock.offline_updates = o.offline_updates
    if o.cost_model == "calibrate":
        cfg.clock.cost_source = "calibrate"
    elif o.cost_model == "shipped":
        cfg.clock.cost, cfg.clock.cost_source = CostModel(), "config"
    elif o.cost_model is not None:
        cfg.clock.cost, cfg.clock.cost_source = CostModel.load(o.cost_model), "config"
    return cfg


def to_run_options(o: MapOptions):
    """The :class:`~.pipeline.RunOptions` of a run (how the sequence is read, held out, evaluated and written)."""
    from .pipeline import RunOptions

    names = {f.name for f in fields(RunOptions)} & {f.name for f in fields(MapOptions)}
    opts = RunOptions(**{n: getattr(o, n) for n in sorted(names)})
    opts.holdout_list = str(o.holdout_list) if o.holdout_list else None
    return opts


def resolve(o: MapOptions):
    """(Config, RunOptions) of a run: the one function behind ``eligsir map``, ``eligsir batch`` and the examples."""
    return to_config(o), to_run_options(o)
