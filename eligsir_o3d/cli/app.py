"""The ``eligsir`` command line: map, demo, eval, export, config, view, render, live, calibrate-color, batch.
Thin: heavy modules are imported inside commands."""

from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

from .commands import COMMANDS, Renderer, _serve_until_interrupted
from .commands import fail as _fail

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False)


class Mechanism(str, Enum):
    views = "views"
    fidelity = "fidelity"
    growth = "growth"


class BadFrame(str, Enum):
    skip = "skip"
    stop = "stop"




class ClockMode(str, Enum):
    cost = "cost"
    updates = "updates"
    realtime = "realtime"


def _version(value: bool) -> None:
    if value:
        from .._version import __version__

        typer.echo(f"eligsir_o3d {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """EliGSiR: budget-aware online RGB-D Gaussian-splatting mapping on Open3D."""


INPUT, POSE, BUDGET, EVAL, OUTPUT, MAPPER = "Input", "Pose", "Budget", "Evaluation", "Output", "Mapper"


@app.command("map")
def map_cmd(
    path: Optional[str] = typer.Argument(None, help="Sequence folder (TUM, Replica, plain folder layout), "
                                         "a ROS 1/2 or RealSense bag, a ScanNet .sens, or 'synthetic'.", show_default=False),
    max_frames: Optional[int] = typer.Option(None, help="Use only the first N frames.", rich_help_panel=INPUT),
    depth_max: Optional[float] = typer.Option(None, help="Depth beyond this (metres) counts as no measurement "
                                              "(default: the config's, 8).", rich_help_panel=INPUT),
    on_bad_frame: Optional[BadFrame] = typer.Option(None, help="What to do with a frame that cannot be read or "
                                                    "used (default: the config's, skip).", rich_help_panel=INPUT),
    config: Optional[Path] = typer.Option(None, help="config.json to start from (e.g. one written by an earlier "
                                          "run); options given here override it.", rich_help_panel=INPUT),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="Override one config key, e.g. --set "
                                   "views.active_size=16 (repeatable; see 'eligsir config').", rich_help_panel=INPUT),
    rerun: Optional[Path] = typer.Option(None, help="Run again what a results folder recorded (its run.json and "
                                         "config.json); only --out and --quiet apply.", rich_help_panel=INPUT),
    pose: str = typer.Option("gt", help="gt | odometry (Open3D frame-to-model) | kiss-icp | colmap (runs SfM over "
                             "the whole recording BEFORE mapping) | PATH to a TUM trajectory file or a COLMAP model "
                             "folder.", rich_help_panel=POSE),
    clock: Optional[ClockMode] = typer.Option(None, help="cost: deterministic, modelled time; updates: "
                                              "deterministic, N updates per frame; realtime: the wall clock "
                                              "(default: the config's, cost).", rich_help_panel=BUDGET),
    realtime: bool = typer.Option(False, "--realtime", help="Same as --clock realtime.", rich_help_panel=BUDGET),
    speed: Optional[float] = typer.Option(None, help="Replay speed: 0.1 gives the mapper 10x the recording's "
                                          "duration (default: the config's, 1).", rich_help_panel=BUDGET),
    updates_per_frame: Optional[int] = typer.Option(None, help="N updates per source frame: selects --clock "
                                                    "updates.", rich_help_panel=BUDGET),
    cost_model: Optional[str] = typer.Option(None, help="--clock cost prices updates with: calibrate (fit this "
                                             "machine, device and renderer once, cached), shipped (the reference "
                                             "machine's fit: reproducible anywhere) or a JSON FILE of terms "
                                             "(default: calibrate; with --config, the file's).",
                                             rich_help_panel=BUDGET),
    refine: int = typer.Option(0, help="Extra post-mapping updates (+N PM map state).", rich_help_panel=BUDGET),
    offline_reference: bool = typer.Option(False, "--offline-reference", help="Offline reference: all frames at "
                                           "once, a long coarse-to-fine schedule (1/4, 1/2, then full "
                                           "resolution).", rich_help_panel=BUDGET),
    offline_updates: int = typer.Option(0, help="Offline reference: length of its schedule (0: 40 updates per "
                                        "source frame).", rich_help_panel=BUDGET),
    holdout_every: int = typer.Option(8, help="Hold out every N-th frame for evaluation (never mapped).",
                                      rich_help_panel=EVAL),
    holdout_list: Optional[Path] = typer.Option(None, help="File of frame indices to hold out instead.",
                                                rich_help_panel=EVAL),
    eval_every: int = typer.Option(100, help="Held-out checkpoint every N updates (0: only at the end).",
                                   rich_help_panel=EVAL),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Results folder (default: runs/map, or "
                                       "runs/map-2, -3, ... if taken; with --rerun DIR: DIR-rerun, likewise).", rich_help_panel=OUTPUT),
    checkpoint_every: int = typer.Option(0, help="Write OUT/checkpoint.pt every N source frames (atomic).",
                                         rich_help_panel=OUTPUT),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoint.pt of an interrupted run.",
                                rich_help_panel=OUTPUT),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the results of another run in OUT (its "
                                   "files are removed first; without it such a folder is refused).",
                                   rich_help_panel=OUTPUT),
    force_unlock: bool = typer.Option(False, "--force-unlock", help="Take over OUT/eligsir.lock although another "
                                      "host's run holds it (make sure that run has ended).", rich_help_panel=OUTPUT),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.", rich_help_panel=OUTPUT),
    device: Optional[str] = typer.Option(None, help="'cpu', 'cuda:0' or 'CUDA:0' (default: the config's, cpu).",
                                         rich_help_panel=MAPPER),
    renderer: Optional[Renderer] = typer.Option(None, help="auto: gsplat on CUDA, else the compiled cpu "
                                                "rasteriser (default: the config's, auto).", rich_help_panel=MAPPER),
    ablate: List[Mechanism] = typer.Option([], help="Swap a mechanism for its plain policy (repeatable; default: "
                                           "the config's, none).", rich_help_panel=MAPPER),
    seed: Optional[int] = typer.Option(None, help="Random seed (default: the config's, 0).", rich_help_panel=MAPPER),
    no_register: bool = typer.Option(False, "--no-register", help="Ignore a separate colour camera (the sidecar's "
                                     "\"color\" block, a recording's two CameraInfos): the depth camera serves both "
                                     "images, depth is not registered.", rich_help_panel=INPUT),
    rgb_topic: Optional[str] = typer.Option(None, help="ROS bag: colour topic (when the bag has several).",
                                            rich_help_panel=INPUT),
    depth_topic: Optional[str] = typer.Option(None, help="ROS bag: depth topic (when the bag has several).",
                                              rich_help_panel=INPUT),
    rgb_info_topic: Optional[str] = typer.Option(None, help="ROS bag: CameraInfo topic of the colour camera.",
                                                 rich_help_panel=INPUT),
    depth_info_topic: Optional[str] = typer.Option(None, help="ROS bag: CameraInfo topic of the depth camera.",
                                                   rich_help_panel=INPUT),
    pose_topic: Optional[str] = typer.Option(None, help="ROS bag: PoseStamped/Odometry topic of the camera's optical "
                                             "frame.", rich_help_panel=POSE),
    pose_frames: Optional[str] = typer.Option(None, help="ROS bag: poses from tf, "
                                              "'world_frame:camera_optical_frame'.", rich_help_panel=POSE),
    pictures: bool = typer.Option(True, "--pictures/--no-pictures", help="Write heldout/*.png comparisons and "
                                  "flythrough.mp4.", rich_help_panel=OUTPUT),
    view: bool = typer.Option(False, "--view", help="Serve a live browser view of the map while mapping (needs "
                              "viser); it stays up afterwards until Ctrl-C.", rich_help_panel=OUTPUT),
    view_port: int = typer.Option(8080, help="--view: port (the next free one if taken).", rich_help_panel=OUTPUT),
    view_host: str = typer.Option("127.0.0.1", help="--view: address to listen on.", rich_help_panel=OUTPUT),
) -> None:
    """Map a recorded RGB-D sequence into a 3D Gaussian map and evaluate it on held-out views."""
    from ..budget import CostModel
    from ..config import Config, apply_override
    from ..run.folder_guard import fresh_folder
    from ..run.pipeline import RunOptions, read_run, run_mapping

    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(levelname)s %(message)s")
    opts = None
    try:
        if rerun is not None:
            if path is not None:
                _fail("give either a sequence PATH or --rerun DIR, not both")
            path, cfg, opts = read_run(rerun)
            opts.progress = not quiet
            out = out or fresh_folder(str(rerun).rstrip("/") + "-rerun")
        else:
            if path is None:
                _fail("missing the sequence PATH (or --rerun DIR)")
            cfg = Config.load(config) if config else Config()
            for item in set_:
                apply_override(cfg, item)
            if device is not None:
                cfg.device = device
            if renderer is not None:
                cfg.renderer = renderer.value
            if seed is not None:
                cfg.seed = seed
            if ablate:
                cfg.ablate = tuple(sorted({a.value for a in ablate}))
            if depth_max is not None:
                cfg.depth_max = depth_max
            mode = _clock_mode(clock, realtime, updates_per_frame)
            if mode is not None:
                cfg.clock.mode = mode
            if updates_per_frame is not None:
                cfg.clock.updates_per_frame = updates_per_frame
            if speed is not None:
                cfg.clock.speed = speed
            if on_bad_frame is not None:
                cfg.clock.on_bad_frame = on_bad_frame.value
            if offline_updates:
                cfg.clock.offline_updates = offline_updates
            if cost_model == "calibrate" or (cost_model is None and config is None):
                cfg.clock.cost_source = "calibrate"
            elif cost_model == "shipped":
                cfg.clock.cost, cfg.clock.cost_source = CostModel(), "config"
            elif cost_model is not None:
                cfg.clock.cost, cfg.clock.cost_source = CostModel.load(cost_model), "config"
            opts = RunOptions(max_frames=max_frames, holdout_every=holdout_every,
                              holdout_list=str(holdout_list) if holdout_list else None, pose=pose,
                              eval_every=eval_every, refine=refine, offline_reference=offline_reference,
                              checkpoint_every=checkpoint_every, resume=resume, progress=not quiet,
                              pictures=pictures)
            seq_opts = dict(rgb_topic=rgb_topic, depth_topic=depth_topic, rgb_info_topic=rgb_info_topic,
                            depth_info_topic=depth_info_topic, pose_topic=pose_topic, pose_frames=pose_frames)
            seq_opts = {k: v for k, v in seq_opts.items() if v is not None}
            if no_register:
                seq_opts["register"] = False
            opts.sequence_options = seq_opts or None
            out = out or fresh_folder("runs/map")
        opts.force_unlock, opts.overwrite = force_unlock, overwrite
        if view:
            opts.view = _live_view(view_host, view_port)
        m = run_mapping(path, out, cfg, opts)
    except KeyboardInterrupt:
        if opts is not None and opts.view is not None:
            opts.view.close()
        hint = ("continue with the same command and --resume" if (Path(out) / "checkpoint.pt").is_file() else
                "no checkpoint was written (--checkpoint-every N makes one): run again with --overwrite")
        _fail(f"interrupted; {hint} (--out {out})", 130)
    except (ValueError, OSError, RuntimeError) as e:
        if opts is not None and opts.view is not None:
            opts.view.close()
        _fail(str(e), getattr(e, "exit_code", 2))  # 3: a results file not written, 4: OUT in use by another run
    _summary(m, out)
    if opts.view is not None:
        opts.view.show_results(out)
        typer.echo(f"the map stays in view at {opts.view.url}  (Ctrl-C to stop)")
        _serve_until_interrupted(opts.view)


def _live_view(host: str, port: int):
    from ..visual.live import LiveView

    from .commands import show_urls

    try:
        live = LiveView(host, port)
    except (ValueError, RuntimeError, OSError) as e:
        _fail(str(e))
    show_urls(live.viewer if hasattr(live, "viewer") else live, host, "live view")
    return live


def _clock_mode(clock, realtime: bool, updates_per_frame: Optional[int]) -> Optional[str]:
    """The clock mode the options ask for (None: the config's); contradicting options are an error."""
    asked = {c for c in (clock.value if clock else None, "realtime" if realtime else None,
                         "updates" if updates_per_frame is not None else None) if c}
    if len(asked) > 1:
        _fail(f"conflicting clock options: {', '.join(sorted(asked))} (--updates-per-frame selects --clock "
              f"updates, --realtime is --clock realtime)")
    return asked.pop() if asked else None


@app.command("config")
def config_cmd(
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="Override a key before printing."),
    config: Optional[Path] = typer.Option(None, help="Start from this config file instead of the defaults."),
) -> None:
    """Print the default config (or a config file's, with overrides) as JSON: every key --set and --config take."""
    import json

    from ..config import Config, apply_override

    try:
        cfg = Config.load(config) if config else Config()
        for item in set_:
            apply_override(cfg, item)
    except (ValueError, OSError) as e:
        _fail(str(e))
    typer.echo(json.dumps(cfg.to_dict(), indent=2))


def _summary(m: dict, out: Path) -> None:
    h = m["heldout"]

    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)

    typer.echo(f"held-out PSNR {f(h['psnr'], '.2f')} dB  SSIM {f(h['ssim'], '.3f')}  depth RMSE {f(h['depth_rmse_m'], '.3f')} m")
    rules = m.get("heldout_by_pose_rule")
    if rules:  # pose refinement: the held-out views' poses moved into the refined frame by each rule
        typer.echo("held-out PSNR by pose rule: " + "  ".join(f"{r} {f(v['psnr'], '.2f')} dB" for r, v in rules.items())
                   + " (given: the poses as they are)")
    typer.echo(f"CVQ-AUC {f(m['cvq_auc'], '.2f')} dB  CUC@20 {f(m['cuc20_final'], '.3f')}  "
               f"Gaussians {m['gaussians']}  updates {m['updates']}  supervised {m['supervised_mpix']:.1f} MPix")
    pol = m.get("policies") or {}
    views, growth = pol.get("views", {}), pol.get("growth", {})
    if "admitted" in views and "seeded" in growth:
        by_scale = ", ".join(f"{k}: {v}" for k, v in pol.get("fidelity", {}).get("updates_by_scale", {}).items())
        typer.echo(f"views admitted {views['admitted']}/{views.get('released', '?')}  updates by scale {{{by_scale}}}  "
                   f"Gaussians seeded {growth['seeded']}, inserted {growth.get('inserted', 0)}, "
                   f"relocated {growth.get('relocated', 0)}")
    typer.echo(f"mapping {m['mapping_time_s']:.1f} s  RTF {f(m['rtf'], '.2f')}  dropped {m['dropped_frames']}  "
               f"renderer {m['renderer']}  state {m['map_state']}")
    typer.echo(f"results in {out.resolve()}")


@app.command()
def demo(
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Results folder (default: runs/demo, or "
                                       "runs/demo-2, ... if taken)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the results of another run in OUT."),
    frames: int = typer.Option(120, help="Frames of the embedded synthetic room."),
    speed: float = typer.Option(0.1, help="Replay speed: 0.1 gives the mapper 10x the recording's duration."),
    device: str = typer.Option("cpu"),
) -> None:
    """Map the embedded synthetic room (no download) and print where the outputs are."""
    from ..config import Config
    from ..run.pipeline import RunOptions, run_mapping

    from ..run.folder_guard import fresh_folder

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    out = out or fresh_folder("runs/demo")
    cfg = Config(device=device)
    cfg.clock.speed = speed  # 0.1: the mapper gets 10x the recording's duration (modelled, deterministic)
    try:
        m = run_mapping("synthetic", out, cfg, RunOptions(max_frames=frames, eval_every=200, overwrite=overwrite,
                                                          sequence_options={"n_frames": frames}))
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e), getattr(e, "exit_code", 2))
    _summary(m, out)


@app.command()
def export(
    map_ply: Path = typer.Argument(..., help="A 3DGS PLY (e.g. runs/kitchen/map.ply)."),
    mesh: Optional[Path] = typer.Option(None, help="Write a TSDF mesh of the map's rendered depth here (.ply/.obj)."),
    point_cloud: Optional[Path] = typer.Option(None, "--point-cloud", help="Write the Gaussian centres here (.ply/.pcd)."),
    poses: Optional[Path] = typer.Option(None, help="TUM trajectory of mesh viewpoints (default: trajectory.txt beside the map)."),
    voxel_size: float = typer.Option(0.02, help="TSDF voxel size in metres."),
    depth_max: float = typer.Option(5.0, help="Ignore rendered depth beyond this (metres)."),
    min_opacity: float = typer.Option(0.1, help="Point cloud: drop Gaussians below this opacity."),
    device: str = typer.Option("cpu"),
) -> None:
    """Export a saved map as an Open3D triangle mesh and/or point cloud."""
    from ..export import export_from_ply

    if mesh is None and point_cloud is None:
        _fail("nothing to do: give --mesh and/or --point-cloud")
    try:
        summary = export_from_ply(map_ply, mesh, point_cloud, poses=poses, voxel_size=voxel_size,
                                  depth_max=depth_max, min_opacity=min_opacity, device=device)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e))
    except MemoryError:
        _fail(f"{map_ply}: not enough memory for this export (try a larger --voxel-size)")
    for k, v in summary.items():
        typer.echo(f"{k}: {v}")


@app.command("eval")
def eval_cmd(
    results: List[Path] = typer.Argument(..., help="Results folders to compare (each with metrics.json)."),
) -> None:
    """Compare results folders side by side (PSNR, SSIM, CVQ-AUC, CUC@20, MPix, Gaussians, time)."""
    from ..eval import compare_results

    missing = [str(r) for r in results if not (r / "metrics.json").is_file()]
    if missing:
        _fail(f"no metrics.json in {', '.join(missing)}")
    try:
        typer.echo(compare_results(results))
    except (ValueError, OSError) as e:
        _fail(str(e))


for _name, _command in COMMANDS.items():  # live, calibrate-color, view, render, batch (cli_commands.py)
    app.command(_name)(_command)


def _register_calibrate() -> None:
    from .calibrate_cmd import calibrate_cmd

    app.command("calibrate")(calibrate_cmd)


_register_calibrate()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
