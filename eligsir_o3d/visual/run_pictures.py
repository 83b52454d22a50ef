"""The pictures every results folder gets (``eligsir map`` without ``--no-pictures``): held-out comparisons
(``heldout/NNNNNN.png``, :mod:`.pictures`) and a fly-through of the final map along the smoothed trajectory
(``flythrough.mp4``, :mod:`.video`). Runs after evaluation, outside mapping time."""

from __future__ import annotations

import logging
import time
from pathlib import Path

log = logging.getLogger("eligsir_o3d")

HELDOUT_PICTURES = 6
FLYTHROUGH_WIDTH = 320  # 320x240 for a 640x480 camera: ~0.1 s a frame with the cpu renderer on 2 cores
FLYTHROUGH_MAX_FRAMES = 240
FLYTHROUGH_FPS = 24.0


def write_result_pictures(out_dir: str | Path, rec, heldout_frames: list, trajectory: dict,
                          render_heldout=None) -> dict:
    """Write the pictures of a run into ``out_dir``. ``rec``: the Reconstructor; ``heldout_frames``: the
    evaluated held-out :class:`Frame` s; ``trajectory``: {frame index: (timestamp, T_world_cam)} of the mapped
    frames; ``render_heldout(frame)``: how the metrics rendered a held-out view (default: at its pose as it is).
    Returns what was written and the seconds it took (for metrics.json)."""
    from .pictures import write_heldout_pictures
    from .video import render_path, smooth_path

    out = Path(out_dir)
    t0 = time.perf_counter()
    render = render_heldout or (lambda f: rec.render(f.T_world_cam, f.camera))
    pics = write_heldout_pictures(out / "heldout", heldout_frames, render, HELDOUT_PICTURES) if heldout_frames else []
    t1 = time.perf_counter()
    summary = {"heldout": [str(p.relative_to(out)) for p in pics], "heldout_s": t1 - t0}
    poses = [T for _, (_, T) in sorted(trajectory.items())]
    if len(poses) >= 2:
        cam = rec.camera.scaled(min(1.0, FLYTHROUGH_WIDTH / rec.camera.width))
        path = smooth_path(poses, n_out=min(len(poses), FLYTHROUGH_MAX_FRAMES))
        video = render_path(lambda c, T: rec.render(T, c), path, cam, video=out / "flythrough.mp4",
                            fps=FLYTHROUGH_FPS)
        summary.update(flythrough=Path(video["video"]).name, flythrough_frames=video["frames"],
                       flythrough_size=video["size"], flythrough_s=time.perf_counter() - t1)
    log.info("pictures: %d held-out comparisons (%.1f s), fly-through %s (%.1f s)", len(pics), summary["heldout_s"],
             summary.get("flythrough", "none"), summary.get("flythrough_s", 0.0))
    return summary
