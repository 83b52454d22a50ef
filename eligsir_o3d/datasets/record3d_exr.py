"""Record3D's "EXR + JPG" export (Library -> the recording -> Export -> EXR + JPG sequence): a folder.

Layout (Record3D's author, marek-simonik/record3d #53, #67, #121; nerfstudio's ``ns-process-data record3d``,
which reads ``rgb/`` and ``metadata.json`` of this export)::

    <export>/EXR_RGBD/metadata.json   the same JSON as the ``metadata`` of a .r3d (see :mod:`.record3d`): "w", "h",
                                      column-major "K", "poses" [qx qy qz qw tx ty tz] camera-to-world in OpenGL
                                      camera axes, optional "dw", "dh", "fps", "frameTimestamps",
                                      "perFrameIntrinsicCoeffs"
    <export>/EXR_RGBD/rgb/N.jpg       colour of frame N (N = 0, 1, ...; .png accepted); names that are not a bare
                                      number (``12(1).jpg``, a copy) are ignored, as nerfstudio does
    <export>/EXR_RGBD/depth/N.exr     depth of frame N: one float32 channel, "R", in metres, at the depth size

This export has no confidence maps, so ``min_confidence`` does not apply; ``max_depth`` does. Either the export
folder or its ``EXR_RGBD`` folder may be given. A frame without a pose or without its depth file is left out and
listed in ``skipped_frames``. EXR files are read with the ``OpenEXR`` package (optional extra ``phone``).
Options: ``max_depth``, ``color_width``, ``fps`` (see :mod:`.phone`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.inputs import check_regular, printable, read_bytes
from .base import DatasetError
from .phone import PhoneOptions, PhoneSequence, probe_sizes, scaled_to
from .record3d import color_camera, frame_timestamps, parse_metadata, poses_from_metadata

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
DEPTH_CHANNELS = ("R", "Y", "Z", "depth")  # Record3D writes "R"; the others are what other tools name depth


def _root(path: Path) -> Path:
    return path / "EXR_RGBD" if (path / "EXR_RGBD" / "metadata.json").is_file() else path


def detect(path: Path) -> bool:
    if not path.is_dir():
        return False
    root = _root(path)
    return (root / "metadata.json").is_file() and (root / "depth").is_dir() and (root / "rgb").is_dir()


def read_exr_depth(path: Path) -> np.ndarray:
    """Depth [h, w] float32 metres from an EXR file (channel "R", else "Y", "Z", "depth", else its only one)."""
    try:
        import OpenEXR
    except ImportError:
        raise DatasetError("reading Record3D's EXR depth needs OpenEXR: pip install OpenEXR "
                           "(or pip install 'eligsir-o3d[phone]')") from None
    if not path.is_file() and not path.is_symlink():
        raise DatasetError(f"{printable(path)}: missing from the export")
    check_regular(path, "depth file", DatasetError)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError / its own types for truncated or foreign files
        raise DatasetError(f"{path}: not a readable EXR image ({e})") from None
    name = next((c for c in DEPTH_CHANNELS if c in channels), None)
    if name is None and len(channels) == 1:
        name = next(iter(channels))
    if name is None:
        raise DatasetError(f"{path}: no depth channel (looked for {', '.join(DEPTH_CHANNELS)}; the file has "
                           f"{', '.join(sorted(channels)) or 'none'})")
    d = np.asarray(channels[name])
    if d.ndim != 2 or d.dtype.kind != "f":
        raise DatasetError(f"{path}: channel {name} is {d.dtype} {d.shape}, expected one float channel")
    return d.astype(np.float32, copy=False)


def _frames(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    out = {}
    for p in folder.iterdir() if folder.is_dir() else ():
        if p.stem.isdigit() and p.suffix.lower() in suffixes:
            out.setdefault(int(p.stem), p)
    return out


def open_record3d_exr(path: Path, *, max_depth: float = 5.0, color_width: int = 640,
                      fps: float | None = None) -> PhoneSequence:
    """Open a Record3D EXR + JPG export (the folder, or its EXR_RGBD folder); see the module docstring."""
    import cv2

    opts = PhoneOptions(0, max_depth, color_width)
    root = _root(Path(path))
    mpath = root / "metadata.json"
    raw = read_bytes(mpath, "metadata", error=DatasetError)
    meta = parse_metadata(raw, str(mpath))
    color_cam = color_camera(meta, str(mpath))
    images, depths = _frames(root / "rgb", IMAGE_SUFFIXES), _frames(root / "depth", (".exr",))
    if not images:
        raise DatasetError(f"{root / 'rgb'}: no N.jpg colour frames (empty export)")
    frames = sorted(images)
    poses = poses_from_metadata(meta)
    keep, skipped = [], []
    for n in frames:
        if n >= len(poses) or poses[n] is None:
            skipped.append(f"{images[n]}: no pose in metadata.json (lost tracking), left out")
        elif n not in depths:
            skipped.append(f"{images[n]}: no depth/{n}.exr beside it, left out")
        else:
            keep.append(n)
    if not keep:
        raise DatasetError(f"{root}: none of the {len(frames)} frames has both a pose and a depth file")
    keep, stamps, late = frame_timestamps(meta, frames, keep, fps, lambda n: str(images[n]))
    skipped += late
    if not keep:
        raise DatasetError(f"{printable(mpath)}: none of the {len(frames)} frames has a usable timestamp")
    # the files' common size (an unreadable or odd-sized file is its own frame's fault, when the stream reads it)
    (dw, dh), n0 = probe_sizes(keep, lambda n: read_exr_depth(depths[n]).shape[::-1], str(root / "depth"))
    if meta.get("dw") is not None and meta.get("dh") is not None and (int(meta["dw"]), int(meta["dh"])) != (dw, dh):
        raise DatasetError(f"{printable(depths[n0])}: depth is {dw}x{dh} (as most depth files) but metadata.json "
                           f"says dw x dh = {meta['dw']}x{meta['dh']}")
    depth_cam = scaled_to(color_cam, dw, dh)

    def native(i: int):
        n = keep[i]
        data = np.frombuffer(read_bytes(images[n], "colour file", 2 ** 28, DatasetError), dtype=np.uint8)
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
        jpeg = images[n].suffix.lower() != ".png"
        if bgr is None or (jpeg and b"\xff\xd9" not in data[-64:].tobytes()):  # a cut-off JPEG decodes silently
            raise DatasetError(f"frame {i}: colour {images[n]} is corrupt or truncated")
        return bgr[..., ::-1].copy(), read_exr_depth(depths[n]), None

    seq = PhoneSequence(native=native, color_native=color_cam, depth_native=depth_cam, opts=opts,
                        where=lambda i: f"{images[keep[i]]} / {depths[keep[i]].name}", name=Path(path).name,
                        path=Path(path), timestamps=stamps,
                        poses=[poses[n] for n in keep], format="record3d_exr")
    seq.skipped_frames = skipped
    seq.frame_numbers = keep  # rgb/N of each frame
    return seq
