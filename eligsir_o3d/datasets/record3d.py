"""Record3D captures (iPhone / iPad LiDAR app): the ``.r3d`` export, a ZIP, or the same files unzipped into a folder.

Layout (checked against Record3D's author's descriptions, marek-simonik/record3d #7, #39, #93, and the public
parsers, nerfstudio's ``record3d_utils``)::

    metadata        JSON: "w", "h" (colour size), "K" (9 numbers, COLUMN-major, for the colour size: K[6], K[7]
                    are cx, cy), "dw", "dh" (depth size; older captures lack them: inferred from the first depth
                    blob and the colour aspect), "fps", "poses" (one [qx, qy, qz, qw, tx, ty, tz] per frame:
                    camera-to-world, ARKit world, OpenGL camera axes), optional "frameTimestamps" (s),
                    optional "perFrameIntrinsicCoeffs" ([fx, fy, cx, cy] a frame for the colour size, newer
                    versions: their median is used, see :func:`color_camera`)
    rgbd/N.jpg      colour of frame N (N = 0, 1, ...)
    rgbd/N.depth    LZFSE-compressed float32 metres, dh x dw, row-major
    rgbd/N.conf     optional, LZFSE-compressed uint8 confidence 0/1/2, dh x dw

Frames are read from the archive one at a time (nothing is extracted). A frame with no pose (``poses`` shorter
than the frames) is left out and listed in ``skipped_frames``. LZFSE comes from ``pyliblzfse`` (optional extra
``phone``). Options: ``min_confidence``, ``max_depth``, ``color_width`` (see :mod:`.phone`).
"""

from __future__ import annotations

import math
import re
import zipfile
from pathlib import Path

import numpy as np

from ..core.camera import Camera, pose_from_tum
from ..io.inputs import MAX_TEXT_BYTES, lzfse_decompress, parse_json, printable, read_bytes, read_zip_member
from .base import DatasetError
from .phone import PhoneOptions, PhoneSequence, gl_to_cv, import_lzfse, probe_size, scaled_to
from .phone_meta import Record3DMeta, usable_stamps, validated

_FRAME = re.compile(r"^rgbd/(\d+)\.jpg$")


def detect(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() == ".r3d"
    return path.is_dir() and (path / "metadata").is_file() and (path / "rgbd").is_dir()


class _Archive:
    """The capture's files by name, from the ZIP or from an unzipped folder."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.zip = None
        if path.is_file():
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError) as e:
                raise DatasetError(f"{path}: not a readable Record3D capture ({e}; truncated, or not a ZIP)") \
                    from None
            self.names = set(self.zip.namelist())
        else:
            self.names = {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()}

    def where(self, name: str) -> str:
        return printable(f"{self.path}:{name}" if self.zip is not None else str(self.path / name))

    def read(self, name: str, max_bytes: int | None = None) -> bytes:
        """Member ``name``, its declared and inflated size capped (``max_bytes``, default the blob cap)."""
        if name not in self.names:
            raise DatasetError(f"{self.where(name)}: missing from the capture")
        cap = {} if max_bytes is None else {"max_bytes": max_bytes}
        if self.zip is None:
            return read_bytes(self.path / name, "capture file", error=DatasetError, **cap)
        try:
            return read_zip_member(self.zip, name, self.where(name), error=DatasetError, **cap)
        except (zipfile.BadZipFile, OSError, EOFError, zipfile.LargeZipFile, NotImplementedError, RuntimeError,
                ValueError) as e:
            if isinstance(e, DatasetError):
                raise
            raise DatasetError(f"{self.where(name)}: cannot read ({e}; truncated capture?)") from None


def parse_metadata(raw: bytes, where: str) -> dict:
    """The capture's metadata JSON (``metadata`` in a .r3d, ``metadata.json`` in the EXR + JPG export), its
    required fields checked; ``where`` names the file in errors."""
    meta = parse_json(raw, where, DatasetError)
    missing = [k for k in ("w", "h", "K", "poses") if not isinstance(meta, dict) or k not in meta]
    if missing:
        raise DatasetError(f"{printable(where)}: missing field(s) {', '.join(missing)}")
    validated(Record3DMeta, meta, where)  # type, finiteness and range of every field, named in the error
    return meta


def _metadata(ar: _Archive) -> dict:
    if "metadata" not in ar.names:
        raise DatasetError(f"{ar.where('metadata')}: no metadata in the capture (is it a Record3D .r3d export?)")
    return parse_metadata(ar.read("metadata", MAX_TEXT_BYTES), ar.where("metadata"))


def intrinsics_from_K(K: list, w: int, h: int, where: str) -> Camera:
    """Record3D's K (9 numbers, column-major: [fx, 0, 0, 0, fy, 0, cx, cy, 1]) -> Camera of the colour size."""
    try:
        M = np.asarray(K, dtype=np.float64).reshape(3, 3).T  # column-major -> the usual row-major matrix
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{where}: K must be 9 numbers, got {K!r:.80}") from None
    if abs(M[2, 2] - 1.0) > 1e-6 or abs(M[0, 2]) < 1 or abs(M[1, 2]) < 1 or abs(M[2, 0]) + abs(M[2, 1]) > 1e-6:
        raise DatasetError(f"{where}: K is not a column-major pinhole matrix [fx 0 0 0 fy 0 cx cy 1]: {K}")
    return Camera(int(w), int(h), float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2]))


def color_camera(meta: dict, where: str) -> Camera:
    """The colour camera of a capture: from ``perFrameIntrinsicCoeffs`` ([fx, fy, cx, cy] a frame, for the colour
    size; newer Record3D versions, where focus moves the focal length a little) as their median, else from K."""
    cam = intrinsics_from_K(meta["K"], meta["w"], meta["h"], where)
    coeffs = meta.get("perFrameIntrinsicCoeffs")
    if not coeffs:
        return cam
    try:
        c = np.asarray(coeffs, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        c = np.zeros(0)
    if c.ndim != 2 or c.shape[1] != 4 or not np.all(np.isfinite(c)) or not np.all(c[:, :2] > 0):
        raise DatasetError(f"{where}: perFrameIntrinsicCoeffs must be [fx, fy, cx, cy] per frame, got "
                           f"{str(coeffs)[:80]}")
    fx, fy, cx, cy = np.median(c, axis=0)
    if not (0 < cx < cam.width and 0 < cy < cam.height):
        raise DatasetError(f"{where}: perFrameIntrinsicCoeffs put the principal point ({cx:.1f}, {cy:.1f}) outside "
                           f"the {cam.width}x{cam.height} colour image")
    return Camera(cam.width, cam.height, float(fx), float(fy), float(cx), float(cy))


def poses_from_metadata(meta: dict) -> list[np.ndarray | None]:
    """Camera-to-world poses [4, 4] in OpenCV camera axes, one per ``poses`` entry (None: lost / malformed)."""
    poses = []
    for p in meta["poses"]:
        try:
            v = np.asarray(p, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError, OverflowError):
            v = np.zeros(0)
        if v.shape != (7,) or not np.all(np.isfinite(v)) or np.linalg.norm(v[:4]) < 1e-6:
            poses.append(None)  # a lost-tracking / malformed entry: the frame is skipped
            continue
        poses.append(gl_to_cv(pose_from_tum(v[4:], v[:4] / np.linalg.norm(v[:4]))))
    return poses


def frame_timestamps(meta: dict, frames: list[int], keep: list[int], fps: float | None,
                     where=str) -> tuple[list[int], list[float], list[str]]:
    """(kept frames, their seconds, reports): ``frameTimestamps`` when it covers every frame, else N / fps. A frame
    whose stamp is not finite or not later than the one before is left out and reported (``where(n)`` names it)."""
    if fps is not None and not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise DatasetError(f"fps must be a positive number of frames per second, got {printable(fps)}")
    rate = float(fps or meta.get("fps") or 30.0)
    stamps = meta.get("frameTimestamps")
    if isinstance(stamps, list) and len(stamps) > max(frames) and fps is None:
        ok, reports = usable_stamps([stamps[n] for n in keep], [f"{where(n)}" for n in keep])
        kept = [n for n, good in zip(keep, ok) if good]
        return kept, [float(stamps[n]) for n in kept], reports
    return keep, [n / rate for n in keep], []


def open_record3d(path: Path, *, min_confidence: int = 1, max_depth: float = 5.0, color_width: int = 640,
                  fps: float | None = None) -> PhoneSequence:
    """Open a Record3D ``.r3d`` capture (or its unzipped folder); see the module docstring."""
    opts = PhoneOptions(min_confidence, max_depth, color_width)
    ar = _Archive(Path(path))
    meta = _metadata(ar)
    mwhere = ar.where("metadata")
    color_cam = color_camera(meta, mwhere)
    frames = sorted(int(m.group(1)) for m in (_FRAME.match(n) for n in ar.names) if m)
    if not frames:
        raise DatasetError(f"{ar.path}: no rgbd/N.jpg frames in the capture (empty recording)")
    import_lzfse()
    if meta.get("dw") is not None and meta.get("dh") is not None:
        dw, dh = int(meta["dw"]), int(meta["dh"])
    else:  # older captures: the blobs' size and the colour aspect say it (an unreadable blob is its frame's fault)
        def blob_size(n: int) -> tuple[int, int]:
            values = len(lzfse_decompress(ar.read(f"rgbd/{n}.depth"), ar.where(f"rgbd/{n}.depth"),
                                          error=DatasetError)) // 4
            w = int(round(np.sqrt(values * color_cam.width / color_cam.height)))
            return w, values // max(w, 1)

        dw, dh = probe_size(frames, blob_size, ar.where("rgbd/*.depth"))
    depth_cam = scaled_to(color_cam, dw, dh)
    poses = poses_from_metadata(meta)
    keep = [n for n in frames if n < len(poses) and poses[n] is not None]
    skipped = [f"{ar.where(f'rgbd/{n}.jpg')}: no pose in metadata (lost tracking), left out"
               for n in frames if n not in set(keep)]
    if not keep:
        raise DatasetError(f"{mwhere}: none of the {len(frames)} frames has a pose")
    keep, timestamps, late = frame_timestamps(meta, frames, keep, fps, lambda n: ar.where(f"rgbd/{n}.jpg"))
    skipped += late
    if not keep:
        raise DatasetError(f"{mwhere}: none of the {len(frames)} frames has a usable timestamp")

    def blob(n: int, ext: str, dtype, required: bool):
        name = f"rgbd/{n}.{ext}"
        if name not in ar.names:
            if required:
                raise DatasetError(f"{ar.where(name)}: missing from the capture")
            return None
        raw = lzfse_decompress(ar.read(name), ar.where(name), error=DatasetError)
        a = np.frombuffer(raw[:len(raw) - len(raw) % np.dtype(dtype).itemsize], dtype=dtype)
        if a.size != dw * dh:
            raise DatasetError(f"{ar.where(name)}: {a.size} values, expected dw x dh = {dw}x{dh} = {dw * dh}")
        return a.reshape(dh, dw)

    def native(i: int):
        import cv2

        n = keep[i]
        data = np.frombuffer(ar.read(f"rgbd/{n}.jpg"), dtype=np.uint8)
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if bgr is None or b"\xff\xd9" not in data[-64:].tobytes():  # libjpeg decodes a cut-off JPEG silently
            raise DatasetError(f"frame {i}: colour {ar.where(f'rgbd/{n}.jpg')} is corrupt or truncated")
        return bgr[..., ::-1].copy(), blob(n, "depth", np.float32, True), blob(n, "conf", np.uint8, False)

    seq = PhoneSequence(native=native, color_native=color_cam, depth_native=depth_cam, opts=opts,
                        where=lambda i: ar.where(f"rgbd/{keep[i]}.jpg"), name=ar.path.stem, path=ar.path,
                        timestamps=timestamps, poses=[poses[n] for n in keep], format="record3d")
    seq.skipped_frames = skipped
    seq.frame_numbers = keep  # rgbd/N of each frame
    return seq
