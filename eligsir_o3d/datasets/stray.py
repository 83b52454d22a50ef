"""Stray Scanner captures (iPhone / iPad LiDAR app): one folder per recording.

Layout (the app's own format description)::

    rgb.mp4               colour video (HEVC on the phone), one video frame per saved frame
    depth/000000.png      uint16 millimetres, 256 x 192 on current devices (``.npy`` of uint16 mm in the app's
                          2021 versions); numbered by frame: a frame the phone gave no depth for has no file
    confidence/000000.png optional, uint8 0/1/2
    camera_matrix.csv     3 x 3 K for the full colour video size
    odometry.csv          one row per frame: header ``timestamp, frame, x, y, z, qx, qy, qz, qw`` (older captures:
                          ``x, y, z, qx, qy, qz, qw`` only, or no header at all), camera-to-world; the app already
                          turned ARKit's camera axes into OpenCV's (it multiplies by a 180-degree turn about x)

Checked against the app's source (strayrobots/scanner: DatasetEncoder, OdometryEncoder, DepthEncoder,
PngEncoder) and its author's scripts (kekeblom/StrayVisualizer). Frames are the depth files' numbers: the
video and the ``frame`` column (or, without it, the row index) are matched by number, so a frame without
depth is left out (``skipped_frames``) rather than shifting the rest. Columns are found by their header names.
The video is decoded in order (a request behind the decoder reopens it), so a stream reads each frame once.
Options: ``min_confidence``, ``max_depth``, ``color_width``, ``fps``
(only used without a timestamp column; the app records at 60 Hz) -- see :mod:`.phone`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..core.camera import Camera, pose_from_tum
from ..io.inputs import check_regular, printable, read_bytes, read_text
from .base import DatasetError
from .image_header import image_size
from .phone import PhoneOptions, PhoneSequence, check_frame_count, probe_size, read_confidence_png, scaled_to
from .phone_meta import OdometryRow, usable_stamps, validated

POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def detect(path: Path) -> bool:
    return path.is_dir() and os.path.lexists(path / "odometry.csv") and (path / "depth").is_dir() and \
        ((path / "rgb.mp4").is_file() or (path / "camera_matrix.csv").is_file())


def read_odometry(path: Path) -> list[dict]:
    """Rows of ``odometry.csv`` as dicts of floats (keys from the header, or :data:`POSE_COLUMNS`)."""
    lines = [ln.strip() for ln in read_text(path, "odometry", error=DatasetError).splitlines() if ln.strip()]
    if not lines:
        raise DatasetError(f"{path}: empty file (no poses)")
    first = [f.strip() for f in lines[0].split(",")]
    try:
        [float(f) for f in first]
        header, body = list(POSE_COLUMNS) if len(first) == 7 else None, list(enumerate(lines, 1))
    except ValueError:
        header, body = [f.lower() for f in first], list(enumerate(lines[1:], 2))
    if header is None or any(c not in header for c in POSE_COLUMNS):
        raise DatasetError(f"{path}: header must name the columns {', '.join(POSE_COLUMNS)} (got "
                           f"{', '.join(first) if header is None else ', '.join(header)})")
    rows = []
    for lineno, line in body:
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != len(header):
            raise DatasetError(f"{path}:{lineno}: expected {len(header)} fields, got {len(fields)}")
        try:
            row = {k: float(v) for k, v in zip(header, fields)}
        except ValueError:
            raise DatasetError(f"{printable(path)}:{lineno}: not a number in {printable(line[:80])!r}") from None
        validated(OdometryRow, row, f"{path}:{lineno}")  # e.g. a frame number that is not finite
        rows.append(row)
    return rows


class _Video:
    """Frames of ``rgb.mp4`` in order, with a reopen when asked for an earlier one."""

    def __init__(self, path: Path) -> None:
        self.path, self.cap, self.next = path, None, 0

    def _open(self) -> None:
        import cv2

        if self.cap is not None:
            self.cap.release()
        self.cap, self.next = cv2.VideoCapture(str(self.path)), 0
        if not self.cap.isOpened():
            raise DatasetError(f"{self.path}: cannot open the video")

    def size(self) -> tuple[int, int]:
        import cv2

        self._open()
        return int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT))

    def frame(self, k: int) -> np.ndarray:
        if self.cap is None or k < self.next:
            self._open()
        while self.next < k:
            if not self.cap.grab():
                raise DatasetError(f"frame {k}: {self.path} ends after {self.next} frames")
            self.next += 1
        ok, bgr = self.cap.read()
        if not ok:
            raise DatasetError(f"frame {k}: {self.path} ends after {self.next} frames")
        self.next += 1
        return bgr[..., ::-1].copy()


def _camera_matrix(path: Path, size: tuple[int, int]) -> Camera:
    import io

    text = read_text(path, "camera matrix", error=DatasetError)
    try:
        K = np.loadtxt(io.StringIO(text), delimiter=",", dtype=np.float64).reshape(3, 3)
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: expected a 3x3 comma-separated camera matrix ({e})") from None
    if not np.all(np.isfinite(K)) or abs(K[2, 2] - 1.0) > 1e-6 or not K[0, 0] > 0 or not K[1, 1] > 0:
        raise DatasetError(f"{path}: not a pinhole camera matrix [[fx 0 cx] [0 fy cy] [0 0 1]]: {K.tolist()}")
    return Camera(size[0], size[1], float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


def _depth_files(folder: Path) -> dict[int, Path]:
    """Depth files by frame number: ``NNNNNN.png`` (the app since 2022) or ``NNNNNN.npy`` (2021 versions)."""
    files: dict[int, Path] = {}
    for p in sorted(folder.glob("*")) if folder.is_dir() else ():
        if p.stem.isdigit() and p.suffix.lower() in (".png", ".npy"):
            if int(p.stem) not in files or p.suffix.lower() == ".png":
                files[int(p.stem)] = p
    return files


def read_depth_mm(path: Path, i: int) -> np.ndarray:
    """Depth [h, w] float32 metres from a uint16 millimetre PNG or .npy (the app's two encodings)."""
    import io

    import cv2

    check_regular(path, f"depth file of frame {i}", DatasetError)
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(io.BytesIO(read_bytes(path, "depth file", 2 ** 28, DatasetError)), allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise DatasetError(f"frame {i}: depth file {path} is not a readable .npy array ({e})") from None
    else:
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        what = "None" if d is None else f"{d.dtype} {d.shape}"
        raise DatasetError(f"frame {i}: depth file {path} is corrupt or not 16-bit single-channel millimetres "
                           f"(got {what})")
    return d.astype(np.float32) / 1000.0


def _depth_size(path: Path) -> tuple[int, int]:
    """(w, h) of a depth file: from a PNG's header, else (a .npy) from its array."""
    if path.suffix.lower() == ".png":
        check_regular(path, "depth file", DatasetError)
        size = image_size(path)
        if size is not None:
            return size
    d = read_depth_mm(path, -1)
    return d.shape[1], d.shape[0]


def _rows_by_frame(path: Path, rows: list[dict], numbers: list[int]) -> dict[int, dict]:
    """odometry.csv rows by frame number (its ``frame`` column, or the row index in older files), every depth
    frame checked to have one."""
    by_frame = {int(r["frame"]): r for r in rows} if rows and "frame" in rows[0] else dict(enumerate(rows))
    if len(by_frame) < len(rows):
        raise DatasetError(f"{printable(path)}: a frame number appears on two rows")
    check_frame_count(path, "poses", len(rows), len(numbers))
    missing = [n for n in numbers if n not in by_frame]
    if missing:
        raise DatasetError(f"{path}: no row for frame {missing[0]:06d} (depth/{missing[0]:06d}), "
                           f"{len(missing)} frame(s) in all")
    return by_frame


def open_stray(path: Path, *, min_confidence: int = 1, max_depth: float = 5.0, color_width: int = 640,
               fps: float = 60.0) -> PhoneSequence:
    """Open a Stray Scanner folder; see the module docstring."""
    opts = PhoneOptions(min_confidence, max_depth, color_width)
    depths = _depth_files(path / "depth")
    if not depths:
        raise DatasetError(f"{path / 'depth'}: no depth PNGs (empty recording)")
    video = _Video(path / "rgb.mp4")
    if not video.path.is_file() and not video.path.is_symlink():
        raise DatasetError(f"{printable(video.path)}: missing (the capture's colour video)")
    check_regular(video.path, "colour video", DatasetError)
    color_cam = _camera_matrix(path / "camera_matrix.csv", video.size())
    numbers = sorted(depths)
    dw, dh = probe_size(numbers, lambda n: _depth_size(depths[n]), str(path / "depth"))
    depth_cam = scaled_to(color_cam, dw, dh)
    odo = path / "odometry.csv"
    rows = _rows_by_frame(odo, read_odometry(odo), numbers)
    skipped = [f"{odo}: frame {n:06d} has no depth/{n:06d} (the phone gave no depth), left out"
               for n in sorted(set(rows) - set(numbers))]
    keep, poses = [], []
    for n in numbers:
        r = rows[n]
        q = np.array([r["qx"], r["qy"], r["qz"], r["qw"]])
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
            skipped.append(f"{odo}: frame {n:06d} has no valid pose (lost tracking), left out")
            continue
        keep.append(n)
        poses.append(pose_from_tum(np.array([r["x"], r["y"], r["z"]]), q / np.linalg.norm(q)))
    if not keep:
        raise DatasetError(f"{odo}: none of the {len(numbers)} frames has a valid pose")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise DatasetError(f"fps must be a positive number of frames per second, got {printable(fps)}")
    timestamps = [rows[n]["timestamp"] if "timestamp" in rows[n] else n / fps for n in keep]
    ok, late = usable_stamps(timestamps, [f"{odo}: frame {n:06d}" for n in keep])
    keep, poses, timestamps = ([x for x, good in zip(v, ok) if good] for v in (keep, poses, timestamps))
    skipped += late
    if not keep:
        raise DatasetError(f"{printable(odo)}: none of the {len(numbers)} frames has a usable timestamp")
    confs = path / "confidence"

    def native(i: int):
        n = keep[i]
        conf = read_confidence_png(confs / f"{depths[n].stem}.png", i)
        return video.frame(n), read_depth_mm(depths[n], i), conf  # the video holds every frame, depth or not

    seq = PhoneSequence(native=native, color_native=color_cam, depth_native=depth_cam, opts=opts,
                        where=lambda i: f"{video.path} / {depths[keep[i]]}", name=path.name, path=path,
                        timestamps=timestamps, poses=poses, format="stray")
    seq.skipped_frames = skipped
    seq.frame_numbers = keep  # NNNNNN of each frame (depth/, confidence/, the video's frame index)
    return seq
