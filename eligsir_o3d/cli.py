"""The ``eligsir`` command line: map, demo, eval, export, batch. Thin: heavy modules are imported inside commands."""

from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="EliGSiR: budget-aware online RGB-D Gaussian-splatting mapping on Open3D.")


class Renderer(str, Enum):
    auto = "auto"
    torch = "torch"
    cpu = "cpu"
    gsplat = "gsplat"


class Mechanism(str, Enum):
    scheduling = "scheduling"
    fidelity = "fidelity"
    growth = "growth"


class BadFrame(str, Enum):
    skip = "skip"
    stop = "stop"


def _fail(msg: str) -> None:
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


@app.command("map")
def map_cmd(
    path: str = typer.Argument(..., help="Sequence folder (TUM, Replica, plain folder layout) or 'synthetic'."),
    out: Path = typer.Option(Path("runs/map"), "--out", "-o", help="Results folder."),
    device: Optional[str] = typer.Option(None, help="'cpu' or 'cuda:0' [default: the config's, else cpu]."),
    renderer: Optional[Renderer] = typer.Option(None, help="auto: gsplat on CUDA, else the compiled cpu rasteriser "
                                                "[default: the config's, else auto]."),
    max_frames: Optional[int] = typer.Option(None, help="Use only the first N frames."),
    holdout_every: int = typer.Option(8, help="Hold out every N-th frame for evaluation (never mapped)."),
    holdout_list: Optional[Path] = typer.Option(None, help="File of frame indices to hold out instead."),
    pose: str = typer.Option("gt", help="gt | odometry (Open3D frame-to-model) | kiss-icp | colmap (runs SfM over the whole recording BEFORE mapping) | PATH to a TUM trajectory file or a COLMAP model folder."),
    realtime: bool = typer.Option(False, "--realtime", help="Real-time replay against the wall clock (frames can drop)."),
    speed: Optional[float] = typer.Option(None, help="Replay speed: 0.1 gives the mapper 10x the recording's duration (both clocks) [default: the config's, else 1]."),
    updates_per_frame: Optional[int] = typer.Option(None, help="Deterministic budget: updates per source frame."),
    ablate: List[Mechanism] = typer.Option([], help="Swap a mechanism for its plain policy (repeatable) [default: the config's, else none]."),
    refine: int = typer.Option(0, help="Extra post-mapping updates (+N PM map state)."),
    offline_reference: bool = typer.Option(False, "--offline-reference", help="Offline reference: all frames at once, long full-res schedule."),
    offline_updates: int = typer.Option(0, help="Offline reference: length of its schedule (0: 30 updates per source frame)."),
    eval_every: int = typer.Option(100, help="Held-out checkpoint every N updates (0: only at the end)."),
    on_bad_frame: Optional[BadFrame] = typer.Option(None, help="What to do with a frame that cannot be read or used [default: the config's, else skip]."),
    checkpoint_every: int = typer.Option(0, help="Write OUT/checkpoint.pt every N source frames (atomic)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoint.pt of an interrupted run."),
    config: Optional[Path] = typer.Option(None, help="config.json to start from (e.g. one written by an earlier run); options given here override it."),
    seed: Optional[int] = typer.Option(None, help="Random seed [default: the config's, else 0]."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Map a recorded RGB-D sequence into a 3D Gaussian map and evaluate it on held-out views."""
    from .config import Config
    from .pipeline import RunOptions, run_mapping

    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(levelname)s %(message)s")
    cfg = Config.load(config) if config else Config()
    if device is not None:
        cfg.device = device
    if renderer is not None:
        cfg.renderer = renderer.value
    if seed is not None:
        cfg.seed = seed
    if ablate:
        cfg.ablate = tuple(sorted({a.value for a in ablate}))
    if updates_per_frame is not None:
        cfg.optim.updates_per_frame = updates_per_frame
    opts = RunOptions(max_frames=max_frames, holdout_every=holdout_every,
                      holdout_list=str(holdout_list) if holdout_list else None, pose=pose, realtime=realtime,
                      speed=speed, eval_every=eval_every, refine=refine, offline_reference=offline_reference,
                      offline_updates=offline_updates,
                      on_bad_frame=on_bad_frame.value if on_bad_frame else None, checkpoint_every=checkpoint_every, resume=resume,
                      progress=not quiet)
    try:
        m = run_mapping(path, out, cfg, opts)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e))
    _summary(m, out)


def _summary(m: dict, out: Path) -> None:
    h = m["heldout"]

    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)

    typer.echo(f"held-out PSNR {f(h['psnr'], '.2f')} dB  SSIM {f(h['ssim'], '.3f')}  depth RMSE {f(h['depth_rmse_m'], '.3f')} m")
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
    out: Path = typer.Option(Path("runs/demo"), "--out", "-o", help="Results folder."),
    frames: int = typer.Option(120, help="Frames of the embedded synthetic room."),
    speed: float = typer.Option(0.1, help="Replay speed: 0.1 gives the mapper 10x the recording's duration."),
    device: str = typer.Option("cpu"),
) -> None:
    """Map the embedded synthetic room (no download) and print where the outputs are."""
    from .config import Config
    from .pipeline import RunOptions, run_mapping

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    cfg = Config(device=device)
    # The mapper gets 10x the recording's duration (modelled, deterministic): a clean map in a few CPU minutes.
    m = run_mapping("synthetic", out, cfg, RunOptions(max_frames=frames, eval_every=200, speed=speed,
                                                      sequence_options={"n_frames": frames}))
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
    from .export import export_from_ply

    if mesh is None and point_cloud is None:
        _fail("nothing to do: give --mesh and/or --point-cloud")
    try:
        summary = export_from_ply(map_ply, mesh, point_cloud, poses=poses, voxel_size=voxel_size,
                                  depth_max=depth_max, min_opacity=min_opacity, device=device)
    except (ValueError, OSError) as e:
        _fail(str(e))
    for k, v in summary.items():
        typer.echo(f"{k}: {v}")


@app.command("eval")
def eval_cmd(
    results: List[Path] = typer.Argument(..., help="Results folders to compare (each with metrics.json)."),
) -> None:
    """Compare results folders side by side (PSNR, SSIM, CVQ-AUC, CUC@20, MPix, Gaussians, time)."""
    from .eval import compare_results

    missing = [str(r) for r in results if not (r / "metrics.json").is_file()]
    if missing:
        _fail(f"no metrics.json in {', '.join(missing)}")
    typer.echo(compare_results(results))


@app.command("batch")
def batch_cmd(
    inputs: List[str] = typer.Argument(..., help="Sequence paths and/or manifest files (.txt/.list/.manifest: one sequence a line, optionally with its own --name --max-frames --pose --speed --config --updates-per-frame --eval-every --holdout-every --seed)."),
    out: Path = typer.Option(Path("runs/batch"), "--out", "-o", help="Batch folder: one results folder per sequence, summary.csv."),
    address: Optional[str] = typer.Option(None, help="Ray cluster to join: 'auto' or ray://host:port [default: a local Ray in this process, or the cluster of `ray job submit`]."),
    cpus_per_task: float = typer.Option(1, help="CPUs per sequence (also its torch/numba thread count)."),
    gpus_per_task: Optional[float] = typer.Option(None, help="GPUs per sequence [default: 1 where the cluster has GPUs, else 0]."),
    max_retries: int = typer.Option(3, help="Retries of a sequence whose worker died; each resumes from its last checkpoint."),
    checkpoint_every: int = typer.Option(50, help="Checkpoint every N source frames (what a retry resumes from)."),
    max_frames: Optional[int] = typer.Option(None, help="Use only the first N frames of each sequence."),
    pose: str = typer.Option("gt", help="Pose source, as for `eligsir map`."),
    speed: Optional[float] = typer.Option(None, help="Replay speed, as for `eligsir map`."),
    updates_per_frame: Optional[int] = typer.Option(None, help="Deterministic budget: updates per source frame."),
    eval_every: int = typer.Option(100, help="Held-out checkpoint every N updates (0: only at the end)."),
    holdout_every: int = typer.Option(8, help="Hold out every N-th frame for evaluation."),
    config: Optional[Path] = typer.Option(None, help="config.json to start every sequence from."),
    seed: Optional[int] = typer.Option(None, help="Random seed [default: the config's, else 0]."),
    device: Optional[str] = typer.Option(None, help="Device inside each task [default: cuda:0 with a GPU per task, else the config's]."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write each sequence's plots."),
) -> None:
    """Map many recorded sequences, one Ray task each; re-running skips finished ones and resumes the others."""
    from .batch import BatchError, format_report, map_many

    try:
        results = map_many(inputs, out, address=address, cpus_per_task=cpus_per_task, gpus_per_task=gpus_per_task,
                           max_retries=max_retries, checkpoint_every=checkpoint_every, max_frames=max_frames,
                           pose=pose, speed=speed, config=str(config) if config else None,
                           updates_per_frame=updates_per_frame, eval_every=eval_every, holdout_every=holdout_every,
                           seed=seed, device=device, plots=plots, echo=typer.echo)
    except (BatchError, ValueError, OSError) as e:
        _fail(str(e))
    for line in format_report(results, out):
        typer.echo(line)
    if any(r.status == "failed" for r in results):
        raise typer.Exit(1)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
