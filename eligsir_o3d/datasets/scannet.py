"""ScanNet ``.sens`` files (the official binary format of ScanNet's SensReader), read lazily frame by frame.

Layout (little endian): uint32 version (4), uint64 + bytes sensor name, colour intrinsic, colour extrinsic, depth
intrinsic, depth extrinsic (4x4 float32 each), int32 colour compression (2 = JPEG; 1 = PNG, 0 = raw RGB also
read), int32 depth compression (1 = zlib uint16; 0 = raw uint16), uint32 colour width, height, depth width,
height, float32 depth shift (1000: millimetres), uint64 frame count; then per frame: 4x4 float32
camera-to-world, uint64 colour and depth timestamps (microseconds), uint64 colour and depth byte counts, the
colour bytes, the depth bytes.

Opening walks the frame headers once, seeking over the image bytes, and keeps only their offsets: a 5 GB scan
opens in a few seconds and ``seq[i]`` reads just frame i. ScanNet marks frames where its tracking failed with
-inf (or NaN) poses: those frames are left out of the sequence with a warning naming them
(``seq.bad_pose_frames`` lists their indices in the file; ``eligsir map`` reports them in metrics.json
``skipped_frames``), like TUM frames without a ground-truth pose.

Colour (1296x968) and depth (640x480) come from two cameras: both intrinsics and ``T_color_depth`` (colour
extrinsic^-1 @ depth extrinsic) are kept on the sequence (see twocam.py); frames use the depth camera, with the
colour resized to it, until depth is registered into the colour camera.
"""

from __future__ import annotations

import struct
import warnings
import zlib
from pathlib import Path

import numpy as np
import open3d as o3d

from ..core.camera import Camera
from .base import DatasetError, RGBDSequence
from .twocam import TwoCameras, combine

COLOR_CODECS = {-1: "unknown", 0: "raw", 1: "png", 2: "jpeg"}
DEPTH_CODECS = {-1: "unknown", 0: "raw_ushort", 1: "zlib_ushort", 2: "occi_ushort"}
_FRAME_HEADER = struct.Struct("<64sQQQQ")


def detect(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".sens"


def _camera(M: np.ndarray, width: int, height: int, where: str) -> Camera:
    try:
        return Camera(int(width), int(height), float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2]))
    except ValueError as e:
        raise DatasetError(f"{where}: {e}") from None


class SensSequence(RGBDSequence):
    """An RGBDSequence over a ``.sens`` file; frames are read (and decoded) one at a time."""

    def __init__(self, *, offsets: list[tuple[int, int, int]], codecs: tuple[int, int], native: tuple[int, ...],
                 cameras: TwoCameras, **kwargs) -> None:
        super().__init__(**cameras.sequence_kwargs("depth"), **kwargs)
        self._offsets = offsets  # per frame: (file offset of the colour bytes, colour bytes, depth bytes)
        self._codecs = codecs
        self._native = native  # colour width, height, depth width, height
        self.cameras = cameras
        self.color_intrinsic, self.depth_intrinsic = cameras.color_intrinsic, cameras.depth_intrinsic
        self.T_color_depth = cameras.T_color_depth
        self.bad_pose_frames: list[int] = []  # indices in the file of frames left out for a -inf/NaN pose
        self.skipped_frames: list[str] = []  # the same, as messages (the pipeline reports them in metrics.json)

    def read_native(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i's colour [Hc, Wc, 3] uint8 RGB and depth [Hd, Wd] uint16 as stored."""
        import cv2

        i = self._index(int(i))
        pos, nc, nd = self._offsets[i]
        where = f"frame {i} of {self.path}"
        with open(self.path, "rb") as f:
            f.seek(pos)
            cbytes, dbytes = f.read(nc), f.read(nd)
        if len(cbytes) != nc or len(dbytes) != nd:
            raise DatasetError(f"{where}: file ends inside the frame (truncated .sens)")
        cw, ch, dw, dh = self._native
        ccodec, dcodec = self._codecs
        if ccodec == 0:
            if nc != cw * ch * 3:
                raise DatasetError(f"{where}: raw colour has {nc} bytes, expected {cw * ch * 3}")
            color = np.frombuffer(cbytes, np.uint8).reshape(ch, cw, 3)
        else:
            bgr = cv2.imdecode(np.frombuffer(cbytes, np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                raise DatasetError(f"{where}: cannot decode the {COLOR_CODECS[ccodec]} colour image")
            color = bgr[..., ::-1]
        try:
            raw = zlib.decompress(dbytes) if dcodec == 1 else dbytes
        except zlib.error as e:
            raise DatasetError(f"{where}: corrupt zlib depth ({e})") from None
        if len(raw) != dw * dh * 2:
            raise DatasetError(f"{where}: depth has {len(raw)} bytes, expected {dw}x{dh}x2 = {dw * dh * 2}")
        depth = np.frombuffer(raw, "<u2").reshape(dh, dw).astype(np.uint16)
        return np.ascontiguousarray(color), depth

    def _read_images(self, i: int) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]:
        color, depth = combine(*self.read_native(i), self.cameras)
        return o3d.t.geometry.Image(o3d.core.Tensor(color)), o3d.t.geometry.Image(o3d.core.Tensor(depth[..., None]))


def open_sens(path: Path, *, fps: float = 30.0, depth_scale: float | None = None) -> SensSequence:
    """Open a ScanNet ``.sens`` file (see the module docstring)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        def read(n: int, what: str) -> bytes:
            b = f.read(n)
            if len(b) != n:
                raise DatasetError(f"{path}: file ends inside the header ({what}); truncated or not a .sens file")
            return b

        (version,) = struct.unpack("<I", read(4, "version"))
        if version != 4:
            raise DatasetError(f"{path}: .sens version {version} is not supported (ScanNet writes version 4)")
        (name_len,) = struct.unpack("<Q", read(8, "sensor name length"))
        if name_len > 1024:
            raise DatasetError(f"{path}: sensor name length {name_len} is implausible; not a .sens file?")
        read(name_len, "sensor name")
        mats = np.frombuffer(read(256, "intrinsics/extrinsics"), "<f4").reshape(4, 4, 4).astype(np.float64)
        ccodec, dcodec = struct.unpack("<ii", read(8, "compression types"))
        cw, ch, dw, dh, shift, n = struct.unpack("<IIIIfQ", read(28, "image sizes"))
        if ccodec not in (0, 1, 2):
            raise DatasetError(f"{path}: colour compression {COLOR_CODECS.get(ccodec, ccodec)!r} is not supported "
                               f"(jpeg, png or raw)")
        if dcodec not in (0, 1):
            raise DatasetError(f"{path}: depth compression {DEPTH_CODECS.get(dcodec, dcodec)!r} is not supported "
                               f"(zlib_ushort or raw_ushort)")
        ccam = _camera(mats[0], cw, ch, f"{path}: colour intrinsics")
        dcam = _camera(mats[2], dw, dh, f"{path}: depth intrinsics")
        offsets, poses, stamps, bad = [], [], [], []
        pos = f.tell()
        for k in range(n):
            head = f.read(_FRAME_HEADER.size)
            if len(head) != _FRAME_HEADER.size:
                raise DatasetError(f"{path}: file ends at frame {k} of {n} (truncated .sens)")
            m, tc, _, nc, nd = _FRAME_HEADER.unpack(head)
            pos += _FRAME_HEADER.size
            if pos + nc + nd > size:
                raise DatasetError(f"{path}: frame {k} of {n} runs past the end of the file (truncated .sens)")
            T = np.frombuffer(m, "<f4").reshape(4, 4).astype(np.float64)
            if not np.all(np.isfinite(T)):
                bad.append(k)
            else:
                offsets.append((pos, nc, nd))
                poses.append(T)
                stamps.append(tc * 1e-6)
            pos += nc + nd
            f.seek(pos)
    if bad:
        shown = ", ".join(str(k) for k in bad[:10]) + (" ..." if len(bad) > 10 else "")
        warnings.warn(f"{path.name}: left out {len(bad)} of {n} frames with an invalid (-inf/NaN) pose: {shown}",
                      stacklevel=3)
    if not offsets:
        raise DatasetError(f"{path}: no frame with a valid pose ({n} frames, {len(bad)} with -inf/NaN poses)")
    stamps = np.asarray(stamps)
    if len(stamps) > 1 and not np.all(np.diff(stamps) > 0):  # ScanNet often stores zeros: fall back to fps
        stamps = np.array([k for k in range(n) if k not in set(bad)], dtype=np.float64) / fps
    T_color_depth = np.linalg.inv(mats[1]) @ mats[3]
    cameras = TwoCameras(ccam, dcam, T_color_depth, registered=False)
    seq = SensSequence(offsets=offsets, codecs=(ccodec, dcodec), native=(cw, ch, dw, dh), cameras=cameras,
                       name=path.stem, path=path, depth_scale=depth_scale or float(shift), timestamps=stamps,
                       poses=poses, dropped_unassociated=len(bad), format="scannet")
    seq.bad_pose_frames = bad
    seq.skipped_frames = [f"{path.name} frame {k} (in the file): invalid (-inf/NaN) pose, left out" for k in bad]
    return seq
