"""Write an RGB-D sequence as a phone capture: Record3D ``.r3d`` or EXR + JPG export, a Stray Scanner folder, a
Polycam raw export.

The readers (record3d.py, record3d_exr.py, stray.py, polycam.py) are tested by writing real frames (7-Scenes, SUN3D) with these
functions and reading them back, as the bag readers are. Each writer follows its app's conventions: OpenGL camera
axes in Record3D and Polycam poses, column-major K in Record3D's metadata, LZFSE float32 depth blobs, millimetre
PNGs. ``depth_size=(w, h)`` writes depth at a phone's resolution (nearest-neighbour samples of the frame's depth,
with the intrinsics scaled to match); by default depth keeps the colour size, so a round trip reads back the same
frames. Confidence is written as high where depth is valid and low elsewhere (2 and 0; Polycam's 8-bit 255
and 0).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import pose_to_tum
from .phone import GL_TO_CV, import_lzfse, scaled_to


def _frames(seq, frames: Sequence[int] | None) -> list[int]:
    idx = list(range(len(seq))) if frames is None else [int(i) for i in frames]
    if seq.poses is None:
        raise ValueError("phone captures carry the phone's poses: the sequence has none")
    return idx


def _images(seq, i: int, depth_size):
    """(colour uint8 [H, W, 3], depth float32 metres [h, w], JPEG bytes of the colour or None) of frame i."""
    import cv2

    item = seq[i]
    rgb = item.rgbd.color.as_tensor().numpy()
    d = item.rgbd.depth.as_tensor().numpy()[..., 0].astype(np.float32) / np.float32(seq.depth_scale)
    if depth_size is not None and tuple(depth_size) != (d.shape[1], d.shape[0]):
        d = cv2.resize(d, tuple(depth_size), interpolation=cv2.INTER_NEAREST)
    jpeg = None
    if item.color_path is not None and item.color_path.suffix.lower() in (".jpg", ".jpeg"):
        jpeg = item.color_path.read_bytes()
    return rgb, d, jpeg


def _jpeg(rgb: np.ndarray, jpeg: bytes | None) -> bytes:
    if jpeg is not None:
        return jpeg
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 97])
    return buf.tobytes()


def _depth_camera(seq, depth_size):
    c = seq.camera
    return c if depth_size is None else scaled_to(c, int(depth_size[0]), int(depth_size[1]))


def write_record3d(seq, out: str | Path, *, frames: Sequence[int] | None = None, depth_size=None,
                   gl_axes: bool = True, column_major: bool = True, metadata: bool = True) -> Path:
    """Write frames of ``seq`` as a Record3D ``.r3d`` ZIP. ``gl_axes=False`` writes the poses without the
    OpenGL flip and ``column_major=False`` writes K row-major (both wrong, to test that the reader's
    conventions matter); ``metadata=False`` leaves the metadata entry out (a bad capture)."""
    lz = import_lzfse()
    out, idx, cam = Path(out), _frames(seq, frames), seq.camera
    dcam = _depth_camera(seq, depth_size)
    poses = []
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as z:
        for n, i in enumerate(idx):
            rgb, d, jpeg = _images(seq, i, depth_size)
            z.writestr(f"rgbd/{n}.jpg", _jpeg(rgb, jpeg))
            z.writestr(f"rgbd/{n}.depth", lz.compress(np.ascontiguousarray(d, dtype=np.float32).tobytes()))
            z.writestr(f"rgbd/{n}.conf", lz.compress(np.where(d > 0, 2, 0).astype(np.uint8).tobytes()))
            T = seq.poses[i] @ GL_TO_CV if gl_axes else seq.poses[i]
            t, q = pose_to_tum(T)
            poses.append([*map(float, q), *map(float, t)])
        meta = _record3d_meta(seq, idx, cam, dcam, poses, column_major=column_major)
        if metadata:
            z.writestr("metadata", json.dumps(meta))
    return out


def _record3d_meta(seq, idx, cam, dcam, poses, column_major=True) -> dict:
    K = cam.K.T.reshape(-1) if column_major else cam.K.reshape(-1)
    return {"w": cam.width, "h": cam.height, "K": [float(x) for x in K], "dw": dcam.width, "dh": dcam.height,
            "fps": 30, "poses": poses, "cameraType": 1, "frameTimestamps": [float(seq.timestamps[i]) for i in idx],
            "initPose": [0, 0, 0, 1, 0, 0, 0]}


def write_record3d_exr(seq, out: str | Path, *, frames: Sequence[int] | None = None, depth_size=None,
                       channel: str = "R", per_frame_intrinsics: Sequence[Sequence[float]] | None = None) -> Path:
    """Write frames of ``seq`` as Record3D's EXR + JPG export: ``out/EXR_RGBD/`` with metadata.json, rgb/N.jpg and
    depth/N.exr (one float32 channel named ``channel``, metres, ZIP-compressed). ``per_frame_intrinsics`` adds
    the newer metadata's ``perFrameIntrinsicCoeffs`` ([fx, fy, cx, cy] per frame). Needs the OpenEXR package."""
    import OpenEXR

    out, idx, cam = Path(out), _frames(seq, frames), seq.camera
    root = out / "EXR_RGBD"
    for sub in ("rgb", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    poses = []
    for n, i in enumerate(idx):
        rgb, d, jpeg = _images(seq, i, depth_size)
        (root / "rgb" / f"{n}.jpg").write_bytes(_jpeg(rgb, jpeg))
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {channel: np.ascontiguousarray(d, dtype=np.float32)}) as f:
            f.write(str(root / "depth" / f"{n}.exr"))
        t, q = pose_to_tum(seq.poses[i] @ GL_TO_CV)
        poses.append([*map(float, q), *map(float, t)])
    meta = _record3d_meta(seq, idx, cam, _depth_camera(seq, depth_size), poses)
    if per_frame_intrinsics is not None:
        meta["perFrameIntrinsicCoeffs"] = [[float(v) for v in c] for c in per_frame_intrinsics]
    (root / "metadata.json").write_text(json.dumps(meta))
    return out


def write_stray(seq, out: str | Path, *, frames: Sequence[int] | None = None, depth_size=None,
                header: str = "timestamp, frame, x, y, z, qx, qy, qz, qw", hevc: bool = False,
                depth_ext: str = "png") -> Path:
    """Write frames of ``seq`` as a Stray Scanner folder. The video is lossless H.264 (``libx264rgb``, qp 0,
    through imageio-ffmpeg) so that a round trip reads back the same colour; ``hevc=True`` writes HEVC (``hvc1``,
    lossy) as the app does. ``header``: the odometry.csv header ("" writes none, as the oldest captures).
    ``depth_ext="npy"`` writes depth as the app's 2021 versions did (uint16 millimetre .npy arrays)."""
    import cv2
    import imageio_ffmpeg

    out, idx, cam = Path(out), _frames(seq, frames), seq.camera
    for sub in ("depth", "confidence"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    K = cam.K
    (out / "camera_matrix.csv").write_text("\n".join(", ".join(f"{v:.10g}" for v in row) for row in K) + "\n")
    codec, pix, params = ("libx265", "yuv420p", ["-tag:v", "hvc1", "-x265-params", "log-level=error"]) if hevc else \
        ("libx264rgb", "rgb24", ["-qp", "0", "-preset", "ultrafast"])
    writer = imageio_ffmpeg.write_frames(str(out / "rgb.mp4"), (cam.width, cam.height), fps=30, codec=codec,
                                         pix_fmt_in="rgb24", pix_fmt_out=pix, output_params=params,
                                         macro_block_size=1, quality=None)
    writer.send(None)
    lines = [header] if header else []
    for n, i in enumerate(idx):
        rgb, d, _ = _images(seq, i, depth_size)
        writer.send(np.ascontiguousarray(rgb))
        mm = np.clip(np.rint(d * 1000.0), 0, 65535).astype(np.uint16)
        if depth_ext == "npy":
            np.save(out / "depth" / f"{n:06d}.npy", mm)
        else:
            cv2.imwrite(str(out / "depth" / f"{n:06d}.png"), mm)
        cv2.imwrite(str(out / "confidence" / f"{n:06d}.png"), np.where(mm > 0, 2, 0).astype(np.uint8))
        t, q = pose_to_tum(seq.poses[i])  # Stray Scanner's poses are already in OpenCV camera axes
        vals = [*t, *q]
        cols = [f"{seq.timestamps[i]:.6f}", f"{n:06d}"] if "timestamp" in header else []
        lines.append(", ".join(cols + [f"{v:.9f}" for v in vals]))
    writer.close()
    (out / "odometry.csv").write_text("\n".join(lines) + "\n")
    return out


def write_polycam(seq, out: str | Path, *, frames: Sequence[int] | None = None, depth_size=None,
                  corrected: bool = False) -> Path:
    """Write frames of ``seq`` as a Polycam raw-data export (``corrected=True``: as corrected_images/ and
    corrected_cameras/, with deliberately wrong poses in cameras/ so that a test sees which one is read)."""
    import cv2

    out, idx, cam = Path(out), _frames(seq, frames), seq.camera
    k = out / "keyframes"
    pre = "corrected_" if corrected else ""
    for sub in (f"{pre}images", f"{pre}cameras", "cameras", "depth", "confidence"):
        (k / sub).mkdir(parents=True, exist_ok=True)
    last = -1
    for n, i in enumerate(idx):
        last = max(last + 1, int(round(seq.timestamps[i] * 1e6)))  # names: the time in microseconds, as Polycam's
        stem = f"{last:d}"
        rgb, d, jpeg = _images(seq, i, depth_size)
        (k / f"{pre}images" / f"{stem}.jpg").write_bytes(_jpeg(rgb, jpeg))
        mm = np.clip(np.rint(d * 1000.0), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(k / "depth" / f"{stem}.png"), mm)
        cv2.imwrite(str(k / "confidence" / f"{stem}.png"), np.where(mm > 0, 255, 0).astype(np.uint8))  # 0/127/255
        T = seq.poses[i] @ GL_TO_CV
        data = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height,
                "blur_score": 100.0}
        data.update({f"t_{r}{c}": float(T[r, c]) for r in range(3) for c in range(4)})
        (k / f"{pre}cameras" / f"{stem}.json").write_text(json.dumps(data))
        if corrected:  # the uncorrected poses, off by 0.5 m: the reader must prefer the corrected ones
            data.update({f"t_{r}3": float(T[r, 3] + 0.5) for r in range(3)})
            (k / "cameras" / f"{stem}.json").write_text(json.dumps(data))
    return out

