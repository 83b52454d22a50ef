"""Polycam raw-data export (iPhone / iPad LiDAR, "Export -> Raw data" with developer mode on): a folder.

Layout (Polycam's own description, PolyCam/polyform README and ``core/capture_folder.py``; nerfstudio's
``ns-process-data polycam``)::

    keyframes/images/<stamp>.jpg        colour (corrected_images/, undistorted, with corrected_cameras/: preferred
                                        when both are present)
    keyframes/cameras/<stamp>.json      per frame: fx, fy, cx, cy, width, height (of the image), blur_score,
                                        t_00 .. t_23: row-major 3 x 4 camera-to-world, ARKit world, OpenGL
                                        camera axes (corrected_cameras/: Polycam's globally optimised poses,
                                        preferred when present)
    keyframes/depth/<stamp>.png         uint16 millimetres, 256 x 192 on current devices
    keyframes/confidence/<stamp>.png    optional, 8-bit: 0 low, 127 medium, 255 high (0/1/2 also read)

Frames are the camera files, in the numeric order of their names; a camera file with missing or malformed pose
fields is left out (``skipped_frames``). Timestamps: ``<stamp>``, the keyframe's time in microseconds by
Polycam's spec (a camera file's ``timestamp`` field instead, where one has it), read in the unit (s, ms, us or
ns) that spaces the keyframes 5 ms to 5 s apart; without them, or with ``fps=`` given, frames are spaced at
``fps`` (default 10 per second). All frames share the first camera's intrinsics (a frame whose image size
differs is an error). The corrected images' black undistortion border is cut off (``crop_border``, 15 pixels
by default, as nerfstudio does; Polycam's README asks to mask it). Options: ``min_confidence``, ``max_depth``,
``color_width``, ``fps`` (see :mod:`.phone`), ``crop_border``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.camera import Camera
from ..io.inputs import check_regular, printable, read_bytes, read_json
from .base import DatasetError
from .image_header import image_size
from .phone import PhoneOptions, PhoneSequence, gl_to_cv, probe_size, read_confidence_png, scaled_to
from .phone_meta import PolycamCamera, validated

T_KEYS = [f"t_{r}{c}" for r in range(3) for c in range(4)]


def detect(path: Path) -> bool:
    k = path / "keyframes"
    return path.is_dir() and k.is_dir() and ((k / "cameras").is_dir() or (k / "corrected_cameras").is_dir())


def _stem_key(p: Path):
    try:
        return (0, float(p.stem), p.stem)
    except ValueError:
        return (1, 0.0, p.stem)


def _timestamps(stamps: list, n: int, fps: float | None) -> list[float]:
    if fps is None and len(stamps) == n and n > 1 and all(isinstance(t, (int, float)) for t in stamps):
        t = np.asarray(stamps, dtype=np.float64)
        step = float(np.median(np.diff(t)))
        for unit in (1.0, 1e-3, 1e-6, 1e-9):
            if np.all(np.diff(t) > 0) and 0.005 <= step * unit <= 5.0:
                return list((t - t[0]) * unit)
    return [k / (fps or 10.0) for k in range(n)]


def _read_camera(path: Path) -> tuple[Camera, np.ndarray | None, object]:
    data = read_json(path, "camera JSON", error=DatasetError)
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if not isinstance(data, dict) or k not in data]
    if isinstance(data, dict) and missing:
        raise DatasetError(f"{printable(path)}: missing field(s) {', '.join(missing)}")
    c = validated(PolycamCamera, data, str(path))  # each field's type, finiteness and range, named in the error
    cam = Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
    try:
        M = np.array([float(data[k]) for k in T_KEYS]).reshape(3, 4)
    except (KeyError, TypeError, ValueError, OverflowError):
        return cam, None, None
    if not np.all(np.isfinite(M)):
        return cam, None, None
    T = np.eye(4)
    T[:3] = M
    stamp = data.get("timestamp")
    if stamp is None and path.stem.isdigit():
        stamp = int(path.stem)  # Polycam names every keyframe's files by its timestamp in microseconds
    return cam, gl_to_cv(T), stamp


def _depth_size(path: Path) -> tuple[int, int]:
    """(w, h) of a 16-bit depth PNG from its header (decoded only when the header cannot be parsed)."""
    import cv2

    check_regular(path, "depth file", DatasetError)
    size = image_size(path)
    if size is not None:
        return size
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise DatasetError(f"{printable(path)}: missing or not a 16-bit single-channel PNG")
    return d.shape[1], d.shape[0]


def _read_frame(i: int, ip: Path, k: Path, name: str):
    """Frame i as exported: colour uint8 [H, W, 3] RGB, depth float32 metres, confidence 0/1/2 or None."""
    import cv2

    dp, cp = k / "depth" / f"{name}.png", k / "confidence" / f"{name}.png"
    for p, what in ((ip, "colour file"), (dp, "depth file")):
        if p.exists() or p.is_symlink():
            check_regular(p, f"{what} of frame {i}", DatasetError)
    bgr = cv2.imread(str(ip), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"frame {i}: colour file {ip} is missing or corrupt")
    if ip.suffix == ".jpg" and b"\xff\xd9" not in read_bytes(ip, "colour file", 2 ** 28, DatasetError)[-64:]:
        raise DatasetError(f"frame {i}: colour file {ip} is truncated (no JPEG end-of-image marker)")
    d = cv2.imread(str(dp), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise DatasetError(f"frame {i}: depth file {dp} is missing, corrupt or not a 16-bit PNG")
    return bgr[..., ::-1].copy(), d.astype(np.float32) / 1000.0, read_confidence_png(cp, i)


def open_polycam(path: Path, *, min_confidence: int = 1, max_depth: float = 5.0, color_width: int = 640,
                 fps: float | None = None, crop_border: int | None = None) -> PhoneSequence:
    """Open a Polycam raw-data export folder; see the module docstring. ``crop_border``: pixels cut from each
    edge of the colour images (None: 15 for the corrected images, whose undistortion leaves a black border, as
    nerfstudio's ns-process-data polycam crops them; 0 for the raw images)."""
    import cv2

    if fps is not None and not fps > 0:
        raise DatasetError(f"fps must be positive, got {fps}")
    opts = PhoneOptions(min_confidence, max_depth, color_width)
    k = path / "keyframes"
    # the corrected images are undistorted and go with the corrected cameras' intrinsics and poses: the two are
    # used together or not at all (as nerfstudio's ns-process-data polycam does)
    corrected = (k / "corrected_images").is_dir() and (k / "corrected_cameras").is_dir()
    cam_dir, img_dir = (k / "corrected_cameras", k / "corrected_images") if corrected else \
        (k / "cameras", k / "images")
    files = sorted(cam_dir.glob("*.json"), key=_stem_key)
    if not files:
        raise DatasetError(f"{cam_dir}: no camera JSON files (empty export)")
    color_cam, names, poses, skipped, stamps = None, [], [], [], []
    for f in files:
        cam, T, stamp = _read_camera(f)
        if color_cam is None:
            color_cam = cam
        elif (cam.width, cam.height) != (color_cam.width, color_cam.height):
            raise DatasetError(f"{f}: image size {cam.width}x{cam.height} differs from the first frame's "
                               f"{color_cam.width}x{color_cam.height}")
        if T is None:
            skipped.append(f"{f}: no valid pose (t_00..t_23), left out")
            continue
        names.append(f.stem)
        poses.append(T)
        stamps.append(stamp)
    if not names:
        raise DatasetError(f"{cam_dir}: none of the {len(files)} camera files has a valid pose")
    dw, dh = probe_size(names, lambda name: _depth_size(k / "depth" / f"{name}.png"), str(k / "depth"))
    depth_cam = scaled_to(color_cam, dw, dh)  # the depth covers the whole image
    b = (15 if corrected else 0) if crop_border is None else int(crop_border)
    if not 0 <= 2 * b < min(color_cam.width, color_cam.height):
        raise DatasetError(f"crop_border must be 0 to {min(color_cam.width, color_cam.height) // 2 - 1} pixels for "
                           f"the {color_cam.width}x{color_cam.height} images of {path}, got {crop_border}")
    shown = Camera(color_cam.width - 2 * b, color_cam.height - 2 * b, color_cam.fx, color_cam.fy,
                   color_cam.cx - b, color_cam.cy - b)

    def image(i: int) -> Path:
        p = img_dir / f"{names[i]}.jpg"
        return p if p.is_file() else img_dir / f"{names[i]}.png"

    def native(i: int):
        rgb, d, conf = _read_frame(i, image(i), k, names[i])
        return rgb[b:rgb.shape[0] - b, b:rgb.shape[1] - b].copy() if b else rgb, d, conf

    seq = PhoneSequence(native=native, color_native=shown, depth_native=depth_cam, opts=opts,
                        where=lambda i: str(image(i)), name=path.name, path=path,
                        timestamps=_timestamps(stamps, len(names), fps), poses=poses, format="polycam")
    seq.skipped_frames = skipped
    seq.frame_names = names
    return seq
