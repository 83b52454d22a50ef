"""Fly-throughs: render a map along a camera path into PNG frames and / or an MP4 video.

    path = smooth_path(poses, n_out=240)                               # jitter-free camera path
    render_path(render_fn, path, camera, out_dir="frames", video="fly.mp4", fps=24)

The path is the mapping trajectory smoothed (Gaussian weights over positions and sign-aligned quaternions), then
resampled to ``n_out`` poses by arc index; a hand-held recording's shake would otherwise shake the video.
Videos are H.264 (yuv420p, ``+faststart``) through the FFmpeg that ``imageio-ffmpeg`` ships (the ``phone`` and
``test`` extras): browsers play those in a ``<video>`` element. Without it they are MPEG-4 Part 2 (``mp4v``)
through OpenCV, which desktop players and QuickTime play but browsers do not (OpenCV's wheels do not encode
H.264).
"""

from __future__ import annotations

import math

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ..core.camera import Camera, check_pose


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    from ..core.camera import rotmat_to_quat

    x, y, z, w = rotmat_to_quat(R)
    return np.array([w, x, y, z])


def _rot(q: np.ndarray) -> np.ndarray:
    from ..core.camera import pose_from_tum

    w, x, y, z = q
    return pose_from_tum(np.zeros(3), np.array([x, y, z, w]))[:3, :3]


def smooth_path(poses: Sequence[np.ndarray], n_out: int | None = None, sigma: float | None = None) -> list[np.ndarray]:
    """Camera-to-world poses smoothed with a Gaussian of ``sigma`` poses (default: 1/40 of the path, at least 2)
    and resampled to ``n_out`` poses (default: as many as given)."""
    P = np.stack([check_pose(T, f"path pose {i}") for i, T in enumerate(poses)])  # [N, 4, 4]
    n = len(P)
    n_out = n if n_out is None else int(n_out)
    if n_out < 1:
        raise ValueError(f"n_out must be >= 1, got {n_out}")
    if n == 1:
        return [P[0].copy() for _ in range(n_out)]
    sigma = max(2.0, n / 40.0) if sigma is None else float(sigma)
    q = np.stack([_quat_wxyz(T[:3, :3]) for T in P])  # [N, 4]
    for i in range(1, n):  # one hemisphere, so that averaging neighbours does not cancel
        if q[i] @ q[i - 1] < 0:
            q[i] = -q[i]
    t = P[:, :3, 3]
    samples = np.linspace(0.0, n - 1.0, n_out)
    out = []
    idx = np.arange(n)
    for s in samples:
        w = np.exp(-0.5 * ((idx - s) / sigma) ** 2) if sigma > 0 else (idx == round(s)).astype(float)
        w /= w.sum()
        qm = w @ q
        T = np.eye(4)
        T[:3, :3] = _rot(qm / np.linalg.norm(qm))
        T[:3, 3] = w @ t
        out.append(T)
    return out


class VideoWriter:
    """Frames ([H, W, 3] uint8 RGB, all one size) -> an MP4 file, written atomically: H.264 through imageio-ffmpeg
    when it is installed (``codec`` says which was used), else ``mp4v`` through OpenCV. H.264 in yuv420p needs
    even sizes: an odd last row or column is dropped."""

    def __init__(self, path: str | Path, fps: float, codec: str = "auto"):
        if codec not in ("auto", "h264", "mp4v"):
            raise ValueError(f"codec must be 'auto', 'h264' or 'mp4v', got {codec!r}")
        self.path = Path(path)
        self.fps = float(fps)
        from ..io.atomic import temp_for  # beside a file; elsewhere for a device, which is never replaced

        self._tmp = temp_for(self.path, ".mp4")
        self._writer = None
        self.frames = 0
        self.codec = codec if codec != "auto" else ("h264" if _have_ffmpeg() else "mp4v")

    def _open(self, w: int, h: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.codec == "h264":
            import imageio_ffmpeg

            self._writer = imageio_ffmpeg.write_frames(
                str(self._tmp), (w - w % 2, h - h % 2), fps=self.fps, codec="libx264", pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p", quality=None, macro_block_size=1,
                output_params=["-crf", "20", "-preset", "veryfast", "-movflags", "+faststart"])
            self._writer.send(None)
            return
        import cv2

        self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
        if not self._writer.isOpened():
            raise OSError(f"could not open a video writer for {self.path} (OpenCV without FFmpeg?)")

    def write(self, rgb: np.ndarray) -> None:
        if self._writer is None:
            self._open(rgb.shape[1], rgb.shape[0])
        if self.codec == "h264":
            h, w = rgb.shape[:2]
            self._writer.send(np.ascontiguousarray(rgb[: h - h % 2, : w - w % 2, :3]))
        else:
            self._writer.write(np.ascontiguousarray(rgb[..., ::-1]))
        self.frames += 1

    def close(self) -> Path:
        if self._writer is None:
            raise ValueError(f"{self.path}: no frames to write")
        if self.codec == "h264":
            try:
                self._writer.close()
            except (RuntimeError, OSError) as e:  # ffmpeg failed (e.g. a full disk)
                self._tmp.unlink(missing_ok=True)
                from ..io.atomic import write_failed

                raise write_failed(self.path, OSError(str(e))) from None
        else:
            self._writer.release()
        _commit_video(self._tmp, self.path, self.frames)
        return self.path


def _have_ffmpeg() -> bool:
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError, OSError):
        return False
    return True


def _commit_video(tmp: Path, path: Path, frames: int) -> None:
    """Rename the finished temporary video over ``path`` once it is on disk whole: OpenCV ignores write errors (a
    full disk gives a truncated file), so it is fsynced and read back (its frame count) first; otherwise ``path``
    keeps its previous content and :class:`~eligsir_o3d.io.atomic.WriteFailed` names it."""
    import os

    import cv2

    from ..io.atomic import WriteFailed, commit_file, write_failed

    try:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        cap = cv2.VideoCapture(str(tmp))
        readable = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
        if readable != frames:
            raise WriteFailed(path, f"{frames} frames written, {readable} readable (disk full?)")
        commit_file(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise write_failed(path, e) from None


@torch.no_grad()
def render_path(render_fn: Callable, poses: Sequence[np.ndarray], camera: Camera, out_dir: str | Path | None = None,
                video: str | Path | None = None, fps: float = 24.0) -> dict:
    """Render ``render_fn(camera, T_world_cam)`` -> RenderOutput at every pose; write ``out_dir/NNNNNN.png``
    and / or ``video``. Returns a summary (frames, size, paths)."""
    from .pictures import _u8, write_png

    if out_dir is None and video is None:
        raise ValueError("render_path: give an output folder and/or a video path")
    writer = VideoWriter(video, fps) if video is not None else None
    for k, T in enumerate(poses):
        rgb = _u8(render_fn(camera, T).color.detach().float().cpu().numpy())
        if out_dir is not None:
            write_png(Path(out_dir) / f"{k:06d}.png", rgb)
        if writer is not None:
            writer.write(rgb)
    summary = {"frames": len(poses), "size": f"{camera.width}x{camera.height}"}
    if out_dir is not None:
        summary["frames_dir"] = str(out_dir)
    if writer is not None:
        summary["video"] = str(writer.close())
    return summary


def map_render_fn(gmap, renderer: str = "auto", device: str = "cpu", background=(0.0, 0.0, 0.0)) -> Callable:
    """``render_fn(camera, T_world_cam)`` for a :class:`GaussianMap` (e.g. one read from a PLY)."""
    from ..render import get_renderer, render_map

    rend = get_renderer(renderer, device)
    bg = torch.tensor(background, dtype=torch.float32, device=gmap.device)

    def render_fn(cam: Camera, T: np.ndarray):
        return render_map(rend, gmap, cam, T, bg)

    return render_fn


def render_map_file(map_ply: str | Path, poses_file: str | Path, out_dir: str | Path | None = None,
                    video: str | Path | None = None, scale: float = 1.0, smooth: float = 0.0, fps: float = 24.0,
                    renderer: str = "auto", device: str = "cpu") -> dict:
    """What ``eligsir render`` runs: a PLY rendered at every pose of a TUM trajectory (camera from the
    ``config.json`` beside the map, else 640x480 fx = fy = 525), scaled by ``scale``; ``smooth`` > 0 smooths the
    path with a Gaussian of that many poses first."""
    from ..export.views import DEFAULT_CAMERA, camera_next_to
    from ..io.ply import load_ply
    from ..pose.trajectory import read_tum_trajectory

    if not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"--scale must be a positive number, got {scale}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    gmap = load_ply(map_ply, device)
    _, poses = read_tum_trajectory(poses_file)
    if smooth > 0:
        poses = smooth_path(poses, sigma=smooth)
    from ..io.guards import check_image_size, refuse_overwriting_inputs

    refuse_overwriting_inputs({"--video": video}, {"the map": map_ply, "--poses": poses_file})
    base = camera_next_to(Path(map_ply)) or DEFAULT_CAMERA
    check_image_size(round(base.width * scale), round(base.height * scale), f"--scale {scale:g}: each frame")
    camera = base.scaled(scale)
    summary = render_path(map_render_fn(gmap, renderer, device), poses, camera, out_dir, video, fps)
    return {"map": str(map_ply), "gaussians": len(gmap), **summary}
