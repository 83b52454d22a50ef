"""RealSense ``.bag`` files (what ``rs-record``, the RealSense Viewer and Open3D's recorder write).

A RealSense bag is a ROS 1 bag in librealsense's layout: ``/file_version``, ``/device_0/info``, per sensor
``/device_0/sensor_<s>/info`` and options (``.../option/Depth Units/value``), per stream
``/device_0/sensor_<s>/<Depth|Color>_<i>/info`` (fps, encoding), ``.../info/camera_info`` (intrinsics),
``.../tf/0`` (extrinsic to the device's reference) and ``.../image/data`` (``sensor_msgs/Image``: Z16 depth as
``mono16``, colour as ``rgb8``/``bgr8``/...).

Frames are read through ``rosbags`` with the ROS bag reader (rosbag.py): random access by frame, exact header
timestamps, nothing decoded until asked. Open3D's ``o3d.t.io.RSBagReader`` reads the same files (the tests check
that it returns the same images, intrinsics and depth scale), but it streams: it drops the first frameset and its
``get_timestamp()`` does not follow the returned frame, so it cannot serve ``seq[i]``. Depth scale: 1 / Depth Units
(1000 for the usual 1 mm). Colour and depth have their own intrinsics and an extrinsic (``T_color_depth``): when
they differ the sequence keeps both cameras (twocam.py) instead of Open3D's align-to-colour. No poses: mapping
tracks with odometry by default; a ``PoseStamped``/``Odometry`` topic added to the bag (not part of librealsense's
layout) is used as for ROS bags.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .base import DatasetError
from .rosbag import BagSequence, open_reader, open_rosbag
from .rosmsg import transform_matrix

_STREAM = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/image/data$")


def detect(path: Path) -> bool:
    if not (path.is_file() and path.suffix.lower() == ".bag"):
        return False
    try:
        reader = open_reader(path)
    except DatasetError:
        return False  # not readable: let the ROS reader report why
    try:
        return any(c.topic == "/file_version" for c in reader.connections) and \
            any(_STREAM.match(c.topic) for c in reader.connections)
    finally:
        reader.close()


def _stream_topics(topics: list[str], kind: str, path: Path) -> str:
    found = sorted(t for t in topics if (m := _STREAM.match(t)) and m.group(3) == kind)
    if not found:
        raise DatasetError(f"{path}: RealSense bag without a {kind.lower()} stream (no "
                           f"/device_0/sensor_*/{kind}_*/image/data topic)")
    return found[0].rsplit("/image/data", 1)[0]


def open_realsense(path: Path, *, max_dt: float = 0.02, depth_scale: float | None = None) -> BagSequence:
    """Open a RealSense ``.bag`` (see the module docstring)."""
    reader = open_reader(path)
    try:
        topics = {c.topic: c for c in reader.connections}
        depth, color = _stream_topics(list(topics), "Depth", path), _stream_topics(list(topics), "Color", path)
        sensor = depth.rsplit("/", 1)[0]
        units, extrinsics = None, {}
        wanted = [c for t, c in topics.items() if t == f"{sensor}/option/Depth Units/value"
                  or t in (f"{depth}/tf/0", f"{color}/tf/0")]
        for c, _, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, c.msgtype)
            if c.topic.endswith("/value"):
                units = float(msg.data)
            else:
                extrinsics[c.topic.split("/tf/")[0]] = transform_matrix(msg)
    finally:
        reader.close()
    if depth_scale is None:
        if units is None or not units > 0:
            raise DatasetError(f"{path}: RealSense bag without a positive 'Depth Units' option on {sensor}")
        depth_scale = 1.0 / units
        if abs(depth_scale - round(depth_scale)) < 1e-3 * depth_scale:  # float32 0.001 -> 1000, not 999.99995
            depth_scale = float(round(depth_scale))
    seq = open_rosbag(path, rgb_topic=f"{color}/image/data", depth_topic=f"{depth}/image/data",
                      rgb_info_topic=f"{color}/info/camera_info", depth_info_topic=f"{depth}/info/camera_info",
                      max_dt=max_dt, depth_scale=depth_scale)
    if depth in extrinsics and color in extrinsics:  # each stream's extrinsic is to the same reference
        seq.T_color_depth = seq.cameras.T_color_depth = np.linalg.inv(extrinsics[color]) @ extrinsics[depth]
    seq.format = "realsense"
    return seq
