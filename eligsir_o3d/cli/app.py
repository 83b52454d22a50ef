"""The ``eligsir`` command line: map, demo, eval, export, config, view, render, live, calibrate-color, batch.
Thin: heavy modules are imported inside commands."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import typer

from .commands import COMMANDS, _serve_until_interrupted, setup_logging
from .commands import fail as _fail
from .map_options import map_options, with_options

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False)


def _version(value: bool) -> None:
    if value:
        from .._version import __version__

        typer.echo(f"eligsir_o3d {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """EliGSiR: budget-aware online RGB-D Gaussian-splatting mapping on Open3D."""


@app.command("map")
@with_options
def map_cmd(**kw) -> None:
    """Map a recorded RGB-D sequence into a 3D Gaussian map and evaluate it on held-out views."""
    # the options are the table of .map_options; run.options.resolve turns them into a Config and RunOptions,
    # as for eligsir batch
    from ..run.options import resolve
    from ..run.pipeline import read_run, run_mapping
    from ..run.folder_guard import fresh_folder

    setup_logging(logging.WARNING if kw["quiet"] else logging.INFO)
    path, out, opts = kw["path"], kw["out"], None
    try:
        if kw["rerun"] is not None:
            if path is not None:
                _fail("give either a sequence PATH or --rerun DIR, not both")
            path, cfg, opts = read_run(kw["rerun"])
            opts.progress = not kw["quiet"]
            out = out or fresh_folder(str(kw["rerun"]).rstrip("/") + "-rerun")
        else:
            if path is None:
                _fail("missing the sequence PATH (or --rerun DIR)")
            cfg, opts = resolve(map_options(kw))
            out = out or fresh_folder("runs/map")
        opts.force_unlock, opts.overwrite = kw["force_unlock"], kw["overwrite"]
        if kw["view"]:
            opts.view = _live_view(kw["view_host"], kw["view_port"])
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


@app.command("config")
def config_cmd(
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="Override a key before printing."),
    config: Optional[Path] = typer.Option(None, help="Start from this config file instead of the defaults."),
    explain: Optional[str] = typer.Option(None, metavar="KEY", help="Print KEY's type, default and rule instead."),
) -> None:
    """Print the default config (or a config file's, with overrides) as JSON: every key --set and --config take."""
    import json

    from ..config import Config, apply_override

    if explain is not None:
        from .config_explain import explain as explain_key

        try:
            typer.echo(explain_key(explain))
        except ValueError as e:
            _fail(str(e))
        return
    try:
        cfg = Config.load(config) if config else Config()
        for item in set_:
            apply_override(cfg, item)
    except (ValueError, OSError) as e:
        _fail(str(e))
    typer.echo(json.dumps(cfg.to_dict(), indent=2))


# what each held-out pose rule means, as the summary prints it (metrics.json's heldout_pose_rule)
POSE_RULE_LABELS = {
    "aligned": "aligned: given poses after one rigid training-pose alignment, the paper's rule",
    "given": "given: the poses as they are",
    "tracked": "tracked: poses from the run's pose source",
}


def _summary(m: dict, out: Path) -> None:
    h = m["heldout"]

    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)

    rule = m.get("heldout_pose_rule")
    where = f" ({POSE_RULE_LABELS[rule]})" if rule in POSE_RULE_LABELS else ""
    typer.echo(f"held-out PSNR {f(h['psnr'], '.2f')} dB{where}  SSIM {f(h['ssim'], '.3f')}  "
               f"depth RMSE {f(h['depth_rmse_m'], '.3f')} m")
    posed = m.get("heldout_pose_origin") or "ground truth"
    if posed != "ground truth":  # a recording without poses: say so next to the figure
        lost = len(m.get("heldout_untracked") or [])
        typer.echo(f"  held-out views at poses {posed}" + (f"; {lost} untrackable view(s) left out" if lost else ""))
    typer.echo(f"CVQ-AUC {f(m['cvq_auc'], '.2f')} dB  CUC@20 {f(m['cuc20_final'], '.3f')}  "
               f"Gaussians {m['gaussians']}  updates {m['updates']}  supervised {m['supervised_mpix']:.1f} MPix")
    pol = m.get("policies") or {}
    views, growth = pol.get("views", {}), pol.get("growth", {})
    if "admitted" in views and "seeded" in growth:
        by_scale = ", ".join(f"{k}: {v}" for k, v in pol.get("fidelity", {}).get("updates_by_scale", {}).items())
        sup = pol.get("supervision", {})
        how = f", {sup['mode']} samples below full size" if sup.get("mode") else ""
        if sup.get("coherence_median") is not None:  # the measured decision (scheduling/supervision.py)
            how += f" (views' detail coherence {sup['coherence_median']:.2f})"
        typer.echo(f"views admitted {views['admitted']}/{views.get('released', '?')}  updates by scale {{{by_scale}}}"
                   f"{how}  Gaussians seeded {growth['seeded']}"
                   + (f" (+{growth['reseeded']} finer for earlier views)" if growth.get("reseeded") else "")
                   + f", inserted {growth.get('inserted', 0)}, "
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
    from ..run.options import MapOptions, resolve
    from ..run.pipeline import run_mapping

    from ..run.folder_guard import fresh_folder

    setup_logging()
    out = out or fresh_folder("runs/demo")
    # speed 0.1: the mapper gets 10x the recording's duration (modelled, deterministic); the config's cost model
    cfg, opts = resolve(MapOptions(device=device, speed=speed, max_frames=frames, eval_every=200,
                                   sequence_options={"n_frames": frames}))
    opts.overwrite = overwrite
    try:
        m = run_mapping("synthetic", out, cfg, opts)
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
    spz: Optional[Path] = typer.Option(None, help="Write the map as SPZ here (compressed splats for web viewers; "
                                       "RUB axes, as the SPZ spec says)."),
    splat: Optional[Path] = typer.Option(None, help="Write the map as .splat here (antimatter15's format)."),
    for_viewers: Optional[Path] = typer.Option(
        None, "--for-viewers", help="Write a 3DGS PLY here that viewers with the fixed 0.3 px^2 low-pass draw as "
        "this package does (the map's low-pass baked in; needs run.json and the poses)."),
) -> None:
    """Export a saved map as an Open3D triangle mesh and/or point cloud, and/or as SPZ / .splat for the web."""
    from ..export import export_from_ply, write_for_viewers, write_web
    from ..export.views import camera_next_to, poses_next_to
    from ..io.ply import load_ply
    from ..io.outputs import check_export_outputs

    if mesh is None and point_cloud is None and spz is None and splat is None and for_viewers is None:
        _fail("nothing to do: give --mesh, --point-cloud, --spz, --splat and/or --for-viewers")
    from ..run.option_table import check_option

    try:
        voxel_size, min_opacity = check_option("voxel_size", voxel_size), check_option("min_opacity", min_opacity)
        depth_max = check_option("depth_max", depth_max)
        check_export_outputs(map_ply, poses, mesh=mesh, point_cloud=point_cloud, spz=spz, splat=splat,
                             for_viewers=for_viewers)  # before anything is read or written
        summary = {}
        if for_viewers is not None:
            summary.update(write_for_viewers(map_ply, for_viewers, poses=poses))
        if spz is not None or splat is not None:
            if not map_ply.is_file():
                raise ValueError(f"{map_ply}: no such map")
            summary.update(write_web(load_ply(map_ply), spz, splat, camera_next_to(map_ply),
                                     poses_next_to(map_ply, poses)))
        if mesh is not None or point_cloud is not None:
            summary.update(export_from_ply(map_ply, mesh, point_cloud, poses=poses, voxel_size=voxel_size,
                                           depth_max=depth_max, min_opacity=min_opacity, device=device))
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e), getattr(e, "exit_code", 2))  # 3: an output could not be written
    except MemoryError:
        _fail(f"{map_ply}: not enough memory for this export (try a larger --voxel-size)")
    for k, v in summary.items():
        typer.echo(f"{k}: {v}")


@app.command("eval")
def eval_cmd(
    results: List[Path] = typer.Argument(..., help="Results folders to compare (each with metrics.json)."),
    spatial_out: Optional[Path] = typer.Option(None, "--spatial-out", help="Two folders of one sequence (A B): "
                                               "where the per-cell delta map A - B goes (default: A)."),
) -> None:
    """Compare results folders side by side (PSNR, SSIM, CVQ-AUC, CUC@20, MPix, Gaussians, time); for two runs of
    one sequence also the per-cell delta map (spatial_delta.png/.json: the paper's spatial figure)."""
    from ..eval import compare_results

    missing = [str(r) for r in results if not (r / "metrics.json").is_file()]
    if missing:
        _fail(f"no metrics.json in {', '.join(missing)}")
    try:
        typer.echo(compare_results(results))
    except (ValueError, OSError) as e:
        _fail(str(e))
    if len(results) == 2:
        from ..eval.spatial import compare_spatial, format_summary

        from ..io.atomic import WriteFailed

        try:
            typer.echo(format_summary(compare_spatial(results[0], results[1], spatial_out)))
        except WriteFailed as e:  # --spatial-out unwritable (read-only, a file, a full disk): exit 3
            _fail(str(e), e.exit_code)
        except (ValueError, FileNotFoundError) as e:
            typer.echo(f"no per-cell comparison: {e}")


for _name, _command in COMMANDS.items():  # live, calibrate-color, view, render, batch (cli_commands.py)
    app.command(_name)(_command)


def _register_calibrate() -> None:
    from .ablate_cmd import ablate_cmd
    from .calibrate_cmd import calibrate_cmd

    app.command("calibrate")(calibrate_cmd)
    app.command("ablate")(ablate_cmd)


_register_calibrate()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
