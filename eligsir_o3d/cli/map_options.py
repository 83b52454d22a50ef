"""The options of ``eligsir map``, grouped by the help panel they appear in: one table, one entry per option, so
the command's body stays short and the options' names are :class:`~eligsir_o3d.run.options.MapOptions`' fields
(or the CLI-only ones at the end)."""

from __future__ import annotations

import inspect
from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

from ..run.option_table import default
from ..run.options import COST_MODEL_RULE
from ..scheduling import ABLATIONS
from .commands import Renderer

INPUT, POSE, BUDGET, EVAL, OUTPUT, MAPPER = "Input", "Pose", "Budget", "Evaluation", "Output", "Mapper"


def ablation(value: str) -> str:
    """One ``--ablate`` value, one of :data:`~eligsir_o3d.scheduling.ABLATIONS`."""
    if value in ABLATIONS:
        return value
    raise ValueError(f"{value!r} is not one of {', '.join(map(repr, ABLATIONS))}.")


class BadFrame(str, Enum):
    skip = "skip"
    stop = "stop"


class ClockMode(str, Enum):
    cost = "cost"
    updates = "updates"
    realtime = "realtime"


def _opt(default, help: str, panel: str, *decls, **kw):
    return typer.Option(default, *decls, help=help, rich_help_panel=panel, **kw)


PATH = ("path", Optional[str], typer.Argument(None, help="Sequence folder (TUM, Replica, plain folder layout), a ROS "
                                              "1/2 or RealSense bag, a ScanNet .sens, a phone capture (Record3D "
                                              ".r3d or EXR + JPG export folder, Stray Scanner folder, Polycam "
                                              "raw-data export), or "
                                              "'synthetic'.",
                                              show_default=False))
INPUT_OPTIONS = [
    ("max_frames", Optional[int], _opt(None, "Use only the first N frames.", INPUT)),
    ("depth_max", Optional[float], _opt(None, "Depth beyond this (metres) counts as no measurement (default: the "
                                        "config's, 8).", INPUT)),
    ("on_bad_frame", Optional[BadFrame], _opt(None, "What to do with a frame that cannot be read or used (default: "
                                              "the config's, skip).", INPUT)),
    ("config", Optional[Path], _opt(None, "config.json to start from (e.g. one written by an earlier run); options "
                                    "given here override it.", INPUT)),
    ("set_", List[str], _opt([], "Override one config key, e.g. --set views.active_size=16 (repeatable; see "
                             "'eligsir config').", INPUT, "--set", metavar="KEY=VALUE")),
    ("rerun", Optional[Path], _opt(None, "Run again what a results folder recorded (its run.json and config.json); "
                                   "only --out and --quiet apply.", INPUT)),
    ("no_register", bool, _opt(False, "Ignore a separate colour camera (the sidecar's \"color\" block, a recording's "
                               "two CameraInfos): the depth camera serves both images, depth is not registered.",
                               INPUT, "--no-register")),
    ("rgb_topic", Optional[str], _opt(None, "ROS bag: colour topic (when the bag has several).", INPUT)),
    ("depth_topic", Optional[str], _opt(None, "ROS bag: depth topic (when the bag has several).", INPUT)),
    ("rgb_info_topic", Optional[str], _opt(None, "ROS bag: CameraInfo topic of the colour camera.", INPUT)),
    ("depth_info_topic", Optional[str], _opt(None, "ROS bag: CameraInfo topic of the depth camera.", INPUT)),
    ("min_confidence", Optional[int], _opt(None, "Phone captures (Record3D .r3d, Stray Scanner, Polycam): drop "
                                           "depth below this ARKit confidence, 0-2 (default 1).", INPUT)),
]
POSE_OPTIONS = [
    ("pose", str, _opt("gt", "gt | odometry (Open3D frame-to-model) | kiss-icp | colmap (runs SfM over the whole "
                       "recording BEFORE mapping) | PATH to a TUM trajectory file or a COLMAP model folder.", POSE)),
    ("pose_topic", Optional[str], _opt(None, "ROS bag: PoseStamped/Odometry topic of the camera's optical frame.",
                                       POSE)),
    ("pose_frames", Optional[str], _opt(None, "ROS bag: poses from tf, 'world_frame:camera_optical_frame'.", POSE)),
]
BUDGET_OPTIONS = [
    ("clock", Optional[ClockMode], _opt(None, "cost: deterministic, modelled time; updates: deterministic, N "
                                        "updates per frame; realtime: the wall clock (default: the config's, "
                                        "cost).", BUDGET)),
    ("realtime", bool, _opt(False, "Same as --clock realtime.", BUDGET, "--realtime")),
    ("speed", Optional[float], _opt(None, "Replay speed: 0.1 gives the mapper 10x the recording's duration "
                                    "(default: the config's, 1).", BUDGET)),
    ("updates_per_frame", Optional[int], _opt(None, "N updates per source frame: selects --clock updates.", BUDGET)),
    ("cost_model", Optional[str], _opt(None, "calibrate | shipped | FILE (default: calibrate; with --config, the "
                                       "file's). " + COST_MODEL_RULE, BUDGET)),
    ("refine", int, _opt(0, "Extra post-mapping updates (+N PM map state).", BUDGET)),
    ("offline_reference", bool, _opt(False, "Offline reference: all frames at once, a long coarse-to-fine schedule "
                                     "(1/4, 1/2, then full resolution).", BUDGET, "--offline-reference")),
    ("offline_updates", int, _opt(0, "Offline reference: length of its schedule (0: 40 updates per source frame).",
                                  BUDGET)),
]
EVAL_OPTIONS = [
    ("holdout_every", int, _opt(default("holdout_every"), "Hold out every N-th frame for evaluation (never mapped; "
                                "0: none).", EVAL)),
    ("holdout_list", Optional[Path], _opt(None, "File of frame indices to hold out instead.", EVAL)),
    ("eval_every", int, _opt(default("eval_every"), "Held-out checkpoint every N updates (0: only at the end).",
                             EVAL)),
]
OUTPUT_OPTIONS = [
    ("out", Optional[Path], _opt(None, "Results folder (default: runs/map, or runs/map-2, -3, ... if taken; with "
                                 "--rerun DIR: DIR-rerun, likewise).", OUTPUT, "--out", "-o")),
    ("checkpoint_every", int, _opt(default("checkpoint_every"), "Write OUT/checkpoint.pt every N source frames "
                                   "(atomic; what --resume continues from; 0: none).", OUTPUT)),
    ("resume", bool, _opt(False, "Continue from OUT/checkpoint.pt of an interrupted run.", OUTPUT, "--resume")),
    ("overwrite", bool, _opt(False, "Replace the results of another run in OUT (its files are removed first; "
                             "without it such a folder is refused).", OUTPUT, "--overwrite")),
    ("force_unlock", bool, _opt(False, "Take over OUT/eligsir.lock although another host's run holds it (make sure "
                                "that run has ended).", OUTPUT, "--force-unlock")),
    ("quiet", bool, _opt(False, "No progress bar.", OUTPUT, "--quiet", "-q")),
    ("formats", str, _opt("ply", "Map files to write: ply, spz, splat, comma-separated (map.ply is always "
                          "written; map.spz / map.splat beside it).", OUTPUT, "--format")),
    ("pictures", bool, _opt(True, "Write heldout/*.png comparisons and flythrough.mp4.", OUTPUT,
                            "--pictures/--no-pictures")),
    ("view", bool, _opt(False, "Serve a live browser view of the map while mapping (needs viser); it stays up "
                        "afterwards until Ctrl-C.", OUTPUT, "--view")),
    ("view_port", int, _opt(8080, "--view: port (the next free one if taken).", OUTPUT)),
    ("view_host", str, _opt("127.0.0.1", "--view: address to listen on.", OUTPUT)),
]
MAPPER_OPTIONS = [
    ("device", Optional[str], _opt(None, "'cpu', 'cuda:0' or 'CUDA:0' (default: the config's, cpu).", MAPPER)),
    ("renderer", Optional[Renderer], _opt(None, "auto: gsplat on CUDA, else the compiled cpu rasteriser (default: "
                                          "the config's, auto).", MAPPER)),
    ("ablate", List[str], _opt([], "Swap a mechanism for its plain policy (repeatable; default: the config's, "
                               "none).", MAPPER, parser=ablation,
                               metavar="[" + "|".join(ABLATIONS) + "]")),
    ("seed", Optional[int], _opt(None, "Random seed (default: the config's, 0).", MAPPER)),
]
PANELS = [INPUT_OPTIONS, POSE_OPTIONS, BUDGET_OPTIONS, EVAL_OPTIONS, OUTPUT_OPTIONS, MAPPER_OPTIONS]
SEQUENCE_OPTIONS = ("rgb_topic", "depth_topic", "rgb_info_topic", "depth_info_topic", "pose_topic", "pose_frames",
                    "min_confidence")
CLI_ONLY = ("path", "set_", "rerun", "no_register", "out", "overwrite", "quiet", "view", "view_port", "view_host",
            *SEQUENCE_OPTIONS)


def with_options(fn):
    """``fn(**options)`` with the table's signature, which typer reads as the command's parameters."""
    params = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=tp)
              for name, tp, default in [PATH, *(o for panel in PANELS for o in panel)]]
    fn.__signature__ = inspect.Signature(params, return_annotation=None)
    return fn


def map_options(kw: dict):
    """The :class:`~eligsir_o3d.run.options.MapOptions` of the command's arguments (enums as their values)."""
    from ..export.web import parse_formats
    from ..run.options import MapOptions

    value = lambda v: v.value if isinstance(v, Enum) else v  # noqa: E731
    o = MapOptions(**{k: value(v) for k, v in kw.items() if k not in CLI_ONLY and k != "ablate"})
    o.ablate = tuple(kw["ablate"])
    o.config = str(kw["config"]) if kw["config"] else None
    o.overrides = list(kw["set_"])
    o.progress = not kw["quiet"]
    o.formats = ",".join(parse_formats(kw["formats"]))  # ValueError naming an unknown format
    if kw["cost_model"] is None and kw["config"] is None:
        o.cost_model = "calibrate"  # eligsir map's default (COST_MODEL_RULE)
    seq = {k: kw[k] for k in SEQUENCE_OPTIONS if kw[k] is not None}
    if kw["no_register"]:
        seq["register"] = False
    o.sequence_options = seq or None
    return o
