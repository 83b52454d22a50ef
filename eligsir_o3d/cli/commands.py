"""``eligsir`` commands around mapping: recordings (``live``, ``calibrate-color``), looking at maps (``view``,
``render``) and many recordings (``batch``). :mod:`.cli` registers them on its app (see ``COMMANDS``); like it, they
import heavy modules inside the command.
"""

from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import List, Optional

import typer

from ..run.option_table import default
from ..run.options import COST_MODEL_RULE


def fail(msg: str, code: int = 2) -> None:
    """One red line on stderr and exit status 2: how every command reports bad input (README: exit codes). Control
    characters in ``msg`` (a file name with a newline) are escaped, so the line stays one line."""
    from ..io.inputs import printable

    typer.secho(f"error: {printable(msg)}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


class _Printable(logging.Filter):
    """Escapes control characters in every log line (names read from a recording cannot forge a line)."""

    def filter(self, record: logging.LogRecord) -> bool:
        from ..io.inputs import printable

        record.msg, record.args = printable(record.getMessage()), ()
        return True


def setup_logging(level: int = logging.INFO) -> None:
    """The commands' logging: ``LEVEL message`` lines on stderr, control characters escaped."""
    logging.basicConfig(level=level, format="%(levelname)s %(message)s")
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _Printable) for f in handler.filters):
            handler.addFilter(_Printable())


_fail = fail


class Renderer(str, Enum):
    auto = "auto"
    torch = "torch"
    cpu = "cpu"
    gsplat = "gsplat"


def calibrate_color_cmd(
    path: str = typer.Argument(..., help="Sequence folder with poses (TUM-style or plain folder layout)."),
    pairs: int = typer.Option(8, help="Frame pairs compared."),
    gap: Optional[int] = typer.Option(None, help="Pair frame i with i + GAP (default: with the first frame that has turned 6 degrees or moved 12 cm)."),
    max_frames: Optional[int] = typer.Option(None, help="Use only the first N frames."),
    stride: int = typer.Option(4, help="Every STRIDE-th depth pixel (x and y) is compared."),
    principal_point: bool = typer.Option(True, "--principal-point/--focal-only", help="Also search the principal point (kept unless clearly identified)."),
    write: bool = typer.Option(False, "--write", help="Store the estimate as the \"color\" block of PATH/intrinsics.json."),
) -> None:
    """Estimate the colour camera's intrinsics by the photometric consistency of depth-warped colour across frames."""
    from ..datasets.color_calibration import calibrate_color, write_estimate
    from ..datasets import open_sequence

    try:
        seq = open_sequence(path)
        result = calibrate_color(seq, pairs=pairs, gap=gap, frames=max_frames, stride=stride,
                                 principal_point=principal_point)
        typer.echo(result.report())
        if write:
            typer.echo(f"wrote the colour camera to {write_estimate(seq, result)}")
    except (ValueError, OSError) as e:
        _fail(str(e))


def live(
    out: Path = typer.Option(Path("runs/live"), "--out", "-o", help="Results folder."),
    replay: Optional[str] = typer.Option(None, help="Replay a recording (a RealSense .bag through Open3D's reader, or anything `map` reads) instead of a camera, at its own pace."),
    frames: Optional[int] = typer.Option(None, help="Stop after N frames."),
    seconds: Optional[float] = typer.Option(None, help="Stop after S seconds."),
    pose: str = typer.Option("odometry", help="Pose source: odometry | kiss-icp."),
    device: str = typer.Option("cpu"),
    config: Optional[Path] = typer.Option(None, help="config.json to start from."),
) -> None:
    """Map a connected RealSense camera live (wall clock; frames drop when the mapper falls behind)."""
    from ..config import Config
    from ..run.live_run import RSBagReplay, RealSenseCamera, SequenceReplay, run_live

    from ..run.option_table import check_option

    setup_logging()
    try:
        frames, seconds = check_option("frames", frames), check_option("seconds", seconds)
        cfg = Config.load(config) if config else Config()  # an unknown key, a folder, /dev/zero: one line
        cfg.device = device
        if replay is None:
            source = RealSenseCamera()
        elif replay.endswith(".bag") and _is_realsense(replay):
            source = RSBagReplay(replay)
        else:
            from ..datasets import open_sequence

            source = SequenceReplay(open_sequence(replay), max_frames=frames)
        s = run_live(source, out, cfg, pose=pose, max_frames=frames, seconds=seconds)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e), getattr(e, "exit_code", 2))  # 4: OUT in use by another run (or its lock file is a link)
    typer.echo(f"{s['source']}: captured {s['captured']}, integrated {s['integrated']}, dropped {s['dropped']}, "
               f"tracking lost {s['lost']}; {s['gaussians']} Gaussians, {s['updates']} updates in {s['wall_s']:.1f} s")
    typer.echo(f"results in {out.resolve()}")


def _is_realsense(path: str) -> bool:
    from ..datasets import rsbag

    return rsbag.detect(Path(path))


def view(
    map_ply: Path = typer.Argument(..., help="A 3DGS PLY (e.g. runs/kitchen/map.ply, or one written by gsplat / 3DGS)."),
    port: int = typer.Option(8080, help="Port to serve on (the next free one if taken; 0: any free port)."),
    host: str = typer.Option("127.0.0.1", help="Address to listen on (0.0.0.0 serves the whole network)."),
    trajectory: Optional[Path] = typer.Option(None, help="TUM trajectory to show as cameras [default: trajectory.txt beside the map]."),
    mesh: Optional[Path] = typer.Option(None, help="A mesh to show as a layer [default: mesh.ply/.obj beside the map]."),
    point_cloud: Optional[Path] = typer.Option(None, "--point-cloud", help="A point cloud layer [default: cloud.ply beside the map]."),
    max_cameras: int = typer.Option(40, help="Camera frustums (and go-to buttons) spread along the trajectory."),
) -> None:
    """Look at a map in the browser: the splats, the trajectory's cameras, the mesh / point cloud."""
    from ..visual.viewer import open_map_viewer

    setup_logging()
    try:
        viewer = open_map_viewer(map_ply, host, port, trajectory, mesh, point_cloud, max_cameras)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e))
    show_urls(viewer, host, "viewer")
    _serve_until_interrupted(viewer)


def show_urls(viewer, host: str, what: str) -> None:
    """Print where ``viewer`` is served; for a wildcard host every address, and that it is on the network."""
    from ..visual.bind_check import NETWORK_WARNING, is_wildcard

    urls = getattr(viewer, "urls", None) or [viewer.url]
    typer.echo(f"{what} at {'  '.join(urls)}  (Ctrl-C to stop)")
    if is_wildcard(host):
        typer.secho(NETWORK_WARNING.format(host=host or "0.0.0.0"), fg=typer.colors.YELLOW, err=True)


def _serve_until_interrupted(viewer) -> None:
    import time

    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        try:
            viewer.close()
        except (RuntimeError, OSError):  # Ctrl-C ends the command cleanly, whatever state the server is in
            pass


def render(
    map_ply: Path = typer.Argument(..., help="A 3DGS PLY (e.g. runs/kitchen/map.ply)."),
    poses: Path = typer.Option(..., help="TUM trajectory (camera-to-world) to render the map along."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Folder for the frames (000000.png, ...)."),
    video: Optional[Path] = typer.Option(None, help="Also (or only) write an MP4 video here."),
    scale: float = typer.Option(1.0, help="Image size relative to the map's camera (config.json beside it, else 640x480)."),
    smooth: float = typer.Option(0.0, help="Smooth the path first with a Gaussian of this many poses (0: as given)."),
    fps: float = typer.Option(24.0, help="Video frame rate."),
    renderer: Renderer = typer.Option(Renderer.auto, help="Renderer backend."),
    device: str = typer.Option("cpu"),
) -> None:
    """Render a map along a camera path into PNG frames and/or a video."""
    from ..visual.video import render_map_file

    from ..run.option_table import check_option

    if out is None and video is None:
        _fail("nothing to do: give --out and/or --video")
    try:
        fps, smooth = check_option("fps", fps), check_option("smooth", smooth)
        summary = render_map_file(map_ply, poses, out, video, scale=scale, smooth=smooth, fps=fps,
                                  renderer=renderer.value, device=device)
    except (ValueError, OSError, RuntimeError) as e:
        _fail(str(e), getattr(e, "exit_code", 2))  # 3: an output could not be written
    except MemoryError:
        _fail(f"{map_ply}: not enough memory to render at --scale {scale:g}; use a smaller --scale")
    for k, v in summary.items():
        typer.echo(f"{k}: {v}")


def batch_cmd(
    inputs: List[str] = typer.Argument(..., help="Sequence paths and/or manifest files (.txt/.list/.manifest: one sequence a line, optionally with its own --name --max-frames --pose --speed --config --updates-per-frame --eval-every --holdout-every --seed --cost-model)."),
    out: Path = typer.Option(Path("runs/batch"), "--out", "-o", help="Batch folder: one results folder per sequence, summary.csv."),
    address: Optional[str] = typer.Option(None, help="Ray cluster to join: 'auto' or ray://host:port [default: a local Ray in this process, or the cluster of `ray job submit`]."),
    cpus_per_task: float = typer.Option(default("cpus_per_task"), help="CPUs per sequence (also its torch/numba thread count; at most what one machine of the cluster has)."),
    gpus_per_task: Optional[float] = typer.Option(None, help="GPUs per sequence [default: 1 where the cluster has GPUs, else 0]."),
    max_retries: int = typer.Option(default("max_retries"), help="Retries of a sequence whose worker died; each resumes from its last checkpoint."),
    checkpoint_every: int = typer.Option(default("checkpoint_every"), help="Checkpoint every N source frames (what a retry resumes from; 0: none)."),
    task_timeout: float = typer.Option(default("task_timeout"), help="Seconds one sequence may take before it is stopped and reported failed (0: from the recording's length and the speed)."),
    max_frames: Optional[int] = typer.Option(None, help="Use only the first N frames of each sequence."),
    pose: str = typer.Option("gt", help="Pose source, as for `eligsir map`."),
    speed: Optional[float] = typer.Option(None, help="Replay speed, as for `eligsir map`."),
    updates_per_frame: Optional[int] = typer.Option(None, help="Deterministic budget: updates per source frame."),
    eval_every: int = typer.Option(default("eval_every"), help="Held-out checkpoint every N updates (0: only at the end)."),
    holdout_every: int = typer.Option(default("holdout_every"), help="Hold out every N-th frame for evaluation (0: none)."),
    config: Optional[Path] = typer.Option(None, help="config.json to start every sequence from."),
    seed: Optional[int] = typer.Option(None, help="Random seed [default: the config's, else 0]."),
    cost_model: Optional[str] = typer.Option(None, help="calibrate | shipped | FILE (default: the config's, shipped). " + COST_MODEL_RULE),
    device: Optional[str] = typer.Option(None, help="Device inside each task [default: cuda:0 with a GPU per task, else the config's]."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write each sequence's plots."),
) -> None:
    """Map many recorded sequences, one Ray task each; re-running skips finished ones and resumes the others."""
    from ..batch import BatchError, format_report, map_many

    try:
        results = map_many(inputs, out, address=address, cpus_per_task=cpus_per_task, gpus_per_task=gpus_per_task,
                           max_retries=max_retries, checkpoint_every=checkpoint_every, max_frames=max_frames,
                           task_timeout=task_timeout,
                           pose=pose, speed=speed, config=str(config) if config else None,
                           updates_per_frame=updates_per_frame, eval_every=eval_every, holdout_every=holdout_every,
                           seed=seed, cost_model=cost_model, device=device, plots=plots, echo=typer.echo)
    except (BatchError, ValueError, OSError) as e:
        _fail(str(e), getattr(e, "exit_code", 2))  # 3: the batch folder cannot be written
    for line in format_report(results, out):
        typer.echo(line)
    if any(r.status == "failed" for r in results):
        raise typer.Exit(1)


# command name -> function, registered on the app by cli.py
COMMANDS = {"calibrate-color": calibrate_color_cmd, "live": live, "view": view, "render": render, "batch": batch_cmd}
