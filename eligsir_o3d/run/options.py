"""One path from a user's options to a run: :class:`MapOptions` (the vocabulary of ``eligsir map``, ``eligsir
batch`` manifests and the examples) -> :func:`to_config` / :func:`to_run_options` -> (:class:`Config`,
:class:`RunOptions`). Every entry point builds its run here, so the same options give the same budget.

Which cost model prices the budget (``--clock cost``) is decided by one rule, :data:`COST_MODEL_RULE`, printed by
``eligsir map --help`` and ``eligsir batch --help``. Light to import (the CLI's help reads it): the config and the
pipeline are imported inside the functions."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from .option_table import check_option, check_options, default

COST_MODELS = ("calibrate", "shipped")  # or the path of a JSON file of terms

COST_MODEL_RULE = ("Cost model (what --clock cost charges an update): --cost-model calibrate fits this machine, "
                   "device and renderer once (cached); shipped is the reference machine's fit, the same budget on "
                   "every machine; FILE is a JSON file of terms. Without --cost-model, 'eligsir map' calibrates "
                   "(unless --config is given: then the file's), while 'eligsir batch', 'eligsir demo', run_mapping "
                   "and Reconstructor use the config's (shipped by default), so a batch spread over machines gets "
                   "one budget. Give the same --cost-model to both to get the same budget.")


@dataclass
class RunOptions:
    """How a sequence is run (the mapper's own settings, the clock included, are the :class:`Config`)."""

    max_frames: int | None = None
    sequence_options: dict | None = None  # passed to open_sequence (e.g. {"n_frames": 240} for the synthetic room)
    holdout_every: int = default("holdout_every")  # frames i with i % holdout_every == holdout_every // 2 held out
    holdout_list: str | None = None  # a text file of frame indices to hold out instead
    pose: str = "gt"  # gt | odometry | kiss-icp | colmap | path to a TUM trajectory
    eval_every: int = default("eval_every")  # held-out checkpoint every N optimisation updates (0 = only at the end)
    # with checkpoints on (eval_every > 0), also one each time the stream has released this share of its frames, so
    # a variant with few, expensive updates still gets a curve over the whole stream
    eval_every_progress: float = 0.1
    eval_sample_stride: int = 2  # regional samples: every 2nd pixel in x and y of each held-out view
    eval_ssim_at_checkpoints: bool = True
    refine: int = 0  # +N post-mapping updates after the drain (map state "+N PM")
    offline_reference: bool = False  # all source frames available at once, long full-resolution schedule
    checkpoint_every: int = default("checkpoint_every")  # frames between checkpoints (0 = none)
    resume: bool = False
    overwrite: bool = False  # replace the results of another run in the folder (eligsir map --overwrite; folder_guard)
    force_unlock: bool = False  # take over another host's lock on the results folder (eligsir map --force-unlock)
    plots: bool = True
    pictures: bool = True  # heldout/*.png comparisons and flythrough.mp4 (eligsir_o3d.visual.run_pictures)
    formats: str = "ply"  # map files: "ply", "spz", "splat", comma-separated (map.ply always; eligsir map --format)
    view: object | None = None  # a live viewer (eligsir_o3d.visual.live.LiveView) fed while mapping; not recorded
    progress: bool = True


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
    holdout_every: int = default("holdout_every")
    holdout_list: str | None = None
    eval_every: int = default("eval_every")
    # mapper
    device: str | None = None
    renderer: str | None = None
    ablate: tuple = ()
    seed: int | None = None
    # output
    checkpoint_every: int = default("checkpoint_every")
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

    for name in ("speed", "updates_per_frame", "seed", "depth_max", "offline_updates", "refine"):
        setattr(o, name, check_option(name, getattr(o, name)))  # one line naming the option, before any work
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


def to_run_options(o: MapOptions) -> RunOptions:
    """The :class:`RunOptions` of a run (how the sequence is read, held out, evaluated and written)."""
    names = {f.name for f in fields(RunOptions)} & {f.name for f in fields(MapOptions)}
    opts = RunOptions(**{n: getattr(o, n) for n in sorted(names)})
    check_options(opts)
    opts.holdout_list = str(o.holdout_list) if o.holdout_list else None
    return opts


def resolve(o: MapOptions):
    """(Config, RunOptions) of a run: the one function behind ``eligsir map``, ``eligsir batch`` and the examples."""
    return to_config(o), to_run_options(o)
