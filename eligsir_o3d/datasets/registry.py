"""Format registry: ``open_sequence(path)`` finds the reader whose layout matches the folder or file.

Readers register a ``detect(path) -> bool`` and an ``open(path, **options) -> RGBDSequence``; detection runs in
registration order (the first match wins), and ``kind=`` skips it. A name ``synthetic`` or ``synthetic:<scene>``
opens the built-in scene instead of a folder.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from . import folder, polycam, record3d, record3d_exr, replica, rosbag, rsbag, scannet, stray, tum
from .base import DatasetError, RGBDSequence
from .synthetic import SyntheticRoom, open_synthetic


@dataclass(frozen=True)
class _Format:
    name: str
    detect: Callable[[Path], bool]
    open: Callable[..., RGBDSequence]
    looks_for: str


_FORMATS: dict[str, _Format] = {}


def register_format(name: str, detect_fn: Callable[[Path], bool], open_fn: Callable[..., RGBDSequence],
                    looks_for: str = "") -> None:
    """Add (or replace) a reader. ``looks_for`` describes the layout for error messages."""
    _FORMATS[name] = _Format(name, detect_fn, open_fn, looks_for or name)


def list_formats() -> list[str]:
    """Names accepted as ``kind=`` (besides "auto"), in detection order; "synthetic" is always available."""
    return [*_FORMATS, "synthetic"]


def _call(fmt_name: str, fn: Callable[..., RGBDSequence], *args, **options) -> RGBDSequence:
    params = inspect.signature(fn).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        unknown = sorted(set(options) - set(params))
        if unknown:
            accepted = [k for k, p in params.items() if p.kind is p.KEYWORD_ONLY]
            raise DatasetError(f"unknown option(s) {', '.join(unknown)} for format {fmt_name!r}; "
                               f"it accepts: {', '.join(accepted) or 'none'}")
    return fn(*args, **options)


def open_sequence(path_or_name: str | Path, kind: str = "auto", *, register: bool = True,
                  **options: Any) -> RGBDSequence:
    """Open a recorded RGB-D sequence (or the synthetic scene) as an :class:`RGBDSequence`.

    Args:
        path_or_name: a sequence folder, a bag, a ``.sens`` or ``.r3d`` file, or ``"synthetic"`` (the embedded
            room; ``"synthetic:NAME"`` for another built-in scene).
        kind: ``"auto"`` (detect the layout from the files) or one of :func:`list_formats`.
        register: False ignores a separate colour camera (the sidecar's ``color`` block or a recording's two
            CameraInfos): depth is not registered and the depth camera serves both images.
        **options: passed to the reader, for example ``max_dt=0.02`` (tum, rosbag, realsense), ``fps=30``
            (replica, folder, scannet), ``depth_scale=``, ``rgb_topic, depth_topic, rgb_info_topic,
            depth_info_topic, pose_topic, pose_frames, intrinsics`` (rosbag), ``n_frames, width, height, seed``
            (synthetic), ``min_confidence, max_depth, color_width`` (record3d, stray, polycam; see :mod:`.phone`).

    Returns:
        The sequence: ``len(seq)`` frames, ``seq.intrinsic`` (``o3d.camera.PinholeCameraIntrinsic``),
        ``seq.depth_scale``, and items with ``rgbd`` (``o3d.t.geometry.RGBDImage``), ``T_world_cam`` (camera-to-world
        [4, 4], None without poses) and ``timestamp`` (seconds).

    Raises:
        DatasetError: the path does not exist, its layout is not recognised, or an option is unknown.

    Example:
        ```python
        from eligsir_o3d.datasets import open_sequence

        seq = open_sequence("synthetic", n_frames=4, width=160, height=120)
        item = seq[0]
        print(len(seq), seq.intrinsic.width, item.T_world_cam.shape)  # 4 160 (4, 4)
        ```
    """
    seq = _open(path_or_name, kind, **options)
    if not register:
        seq.ignore_color_camera()
    return seq


def _open(path_or_name: str | Path, kind: str, **options) -> RGBDSequence:
    text = str(path_or_name)
    if kind == "synthetic" or (kind == "auto" and (text == "synthetic" or text.startswith("synthetic:"))):
        scene = text.split(":", 1)[1] if text.startswith("synthetic:") else "room"
        sig = inspect.signature(SyntheticRoom.__init__).parameters
        unknown = sorted(set(options) - set(sig))
        if unknown:
            raise DatasetError(f"unknown option(s) {', '.join(unknown)} for the synthetic scene; it accepts: "
                               f"{', '.join(k for k in sig if k != 'self')}")
        return open_synthetic(scene, **options)
    path = Path(path_or_name).expanduser()
    if not path.exists():
        raise DatasetError(f"sequence folder {path} does not exist")
    if kind != "auto":
        if kind not in _FORMATS:
            raise DatasetError(f"unknown format {kind!r}; available: {', '.join(list_formats())}")
        return _call(kind, _FORMATS[kind].open, path, **options)
    for fmt in _FORMATS.values():
        if fmt.detect(path):
            return _call(fmt.name, fmt.open, path, **options)
    looked = "\n".join(f"  - {f.name}: {f.looks_for}" for f in _FORMATS.values())
    what = "sequence layout" if path.is_dir() else "file type (a sequence is a folder, a bag, a .sens or a .r3d file)"
    raise DatasetError(f"{path}: unrecognised {what}; known layouts:\n{looked}")


register_format("tum", tum.detect, tum.open_tum, "rgb.txt + depth.txt (+ groundtruth.txt), TUM RGB-D")
register_format("replica", replica.detect, replica.open_replica,
                "results/frame*.jpg + results/depth*.png + traj.txt, NICE-SLAM Replica")
# before "folder": the export's rgb/ + depth/ would look like a plain folder missing its intrinsics.json
register_format("record3d_exr", record3d_exr.detect, record3d_exr.open_record3d_exr,
                "Record3D EXR + JPG export: [EXR_RGBD/] metadata.json + rgb/N.jpg + depth/N.exr")
register_format("folder", folder.detect, folder.open_folder, "color/ (or rgb/) + depth/ + intrinsics.json")
register_format("realsense", rsbag.detect, rsbag.open_realsense,
                "RealSense .bag (librealsense layout: /file_version, /device_0/sensor_*/Depth_0, Color_0)")
register_format("rosbag", rosbag.detect, rosbag.open_rosbag,
                "ROS 1 .bag, or ROS 2 bag folder (metadata.yaml + .db3/.mcap): Image/CompressedImage + depth Image")
register_format("scannet", scannet.detect, scannet.open_sens, "a ScanNet .sens file")
register_format("record3d", record3d.detect, record3d.open_record3d,
                "Record3D .r3d export (ZIP: metadata + rgbd/N.jpg, N.depth, N.conf), or its unzipped folder")
register_format("stray", stray.detect, stray.open_stray,
                "Stray Scanner folder: rgb.mp4 + depth/*.png + camera_matrix.csv + odometry.csv")
register_format("polycam", polycam.detect, polycam.open_polycam,
                "Polycam raw-data export: keyframes/{images,cameras,depth}/ (corrected_* preferred)")
