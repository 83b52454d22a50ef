"""ROS messages -> arrays: images, depth, CameraInfo, poses and a small tf buffer (for rosbag.py and rsbag.py).

Works on messages deserialised by ``rosbags`` from ROS 1 or ROS 2 bags (the two spell CameraInfo's matrices
``K``/``k``). Poses are camera-to-world 4x4 float64 in the camera's OpenCV axes (x right, y down, z forward):
a pose topic or tf frame must therefore be the camera's *optical* frame (REP-103 ``*_optical_frame``).
"""

from __future__ import annotations

import struct
from collections import deque
from types import SimpleNamespace

import numpy as np

from ..core.camera import Camera, pose_from_tum
from .base import DatasetError

COLOR_ENCODINGS = {"rgb8": (3, False), "bgr8": (3, True), "rgba8": (4, False), "bgra8": (4, True),
                   "mono8": (1, False), "8UC1": (1, False), "8UC3": (3, True)}  # (channels, BGR order)
DEPTH_ENCODINGS = {"16UC1": "millimetres", "mono16": "millimetres", "32FC1": "metres"}
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped")
TF_TYPE = "tf2_msgs/msg/TFMessage"
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"


def import_rosbags() -> SimpleNamespace:
    """The parts of ``rosbags`` we use, imported on first need (it is an optional dependency)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as e:
        raise DatasetError(f"reading or writing ROS bags needs the rosbags package: pip install 'eligsir-o3d[bags]' "
                           f"(or pip install rosbags) ({e})") from None
    return SimpleNamespace(AnyReader=AnyReader, Writer1=Writer1, Writer2=Writer2, StoragePlugin=StoragePlugin,
                           Stores=Stores, get_types_from_msg=get_types_from_msg, get_typestore=get_typestore)


def header_stamp(raw: bytes | memoryview, ros1: bool) -> float:
    """Header stamp (s) of a serialised message whose first field is a std_msgs/Header, without deserialising it.

    ROS 1: uint32 seq, uint32 sec, uint32 nsec. ROS 2 CDR: 4-byte encapsulation (byte 1: 1 = little endian), then
    int32 sec, uint32 nanosec.
    """
    if ros1:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<iI" if raw[1] == 1 else ">iI", raw, 4)
    return sec + nsec * 1e-9


def stamp_seconds(stamp) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def _rows(msg, channels: int, dtype: np.dtype, where: str) -> np.ndarray:
    """The image's pixels [H, W, C] honouring ``step`` (row padding) and ``is_bigendian``."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * channels * itemsize or data.size < h * step:
        raise DatasetError(f"{where}: image data holds {data.size} bytes, too few for {w}x{h} {msg.encoding} "
                           f"with step {step}")
    rows = data[:h * step].reshape(h, step)[:, :w * channels * itemsize]
    a = np.ascontiguousarray(rows).view(dtype)  # native byte order (Open3D refuses explicit '<' arrays)
    if itemsize > 1 and bool(msg.is_bigendian) != (np.little_endian is False):
        a = a.byteswap()
    return a.reshape(h, w, channels)


def color_from_msg(msg, msgtype: str, where: str) -> np.ndarray:
    """Colour [H, W, 3] uint8 RGB from a sensor_msgs Image (rgb8, bgr8, rgba8, bgra8, mono8) or CompressedImage."""
    if msgtype == COMPRESSED_TYPE:
        import cv2

        a = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if a is None:
            raise DatasetError(f"{where}: cannot decode the compressed colour image (format {msg.format!r})")
        return np.ascontiguousarray(a[..., ::-1])
    enc = msg.encoding
    if enc not in COLOR_ENCODINGS:
        raise DatasetError(f"{where}: colour encoding {enc!r} is not supported "
                           f"(supported: {', '.join(COLOR_ENCODINGS)})")
    channels, bgr = COLOR_ENCODINGS[enc]
    a = _rows(msg, channels, np.uint8, where)
    if channels == 1:
        return np.repeat(a, 3, axis=2)
    a = a[..., :3]
    return np.ascontiguousarray(a[..., ::-1] if bgr else a)


def depth_from_msg(msg, where: str) -> np.ndarray:
    """Depth [H, W]: uint16 millimetres (16UC1, mono16) or float32 metres (32FC1, NaN/inf -> 0)."""
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise DatasetError(f"{where}: depth encoding {enc!r} is not supported "
                           f"(supported: 16UC1 or mono16 in millimetres, 32FC1 in metres)")
    if enc == "32FC1":
        d = _rows(msg, 1, np.float32, where)[..., 0].copy()
        d[~np.isfinite(d)] = 0.0
        return d
    return _rows(msg, 1, np.uint16, where)[..., 0].copy()


def camera_from_info(msg, where: str) -> Camera:
    K = np.asarray(getattr(msg, "K", None) if hasattr(msg, "K") else msg.k, dtype=np.float64).reshape(-1)
    if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise DatasetError(f"{where}: CameraInfo has no usable intrinsics (K={K.tolist()}, "
                           f"{msg.width}x{msg.height})")
    return Camera(int(msg.width), int(msg.height), float(K[0]), float(K[4]), float(K[2]), float(K[5]))


def transform_matrix(p) -> np.ndarray:
    """geometry_msgs Pose or Transform -> 4x4."""
    t = p.position if hasattr(p, "position") else p.translation
    q = p.orientation if hasattr(p, "orientation") else p.rotation
    qv = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not np.all(np.isfinite(qv)) or np.linalg.norm(qv) < 1e-6:
        raise DatasetError(f"invalid quaternion {qv.tolist()}")
    return pose_from_tum(np.array([t.x, t.y, t.z], dtype=np.float64), qv / np.linalg.norm(qv))


def pose_from_msg(msg, msgtype: str) -> np.ndarray:
    """Camera-to-world pose of PoseStamped, PoseWithCovarianceStamped, Odometry or TransformStamped."""
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return transform_matrix(msg.transform)
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    return transform_matrix(pose)


class TfBuffer:
    """Transforms from /tf (time series per edge) and /tf_static; ``lookup`` chains them between two frames."""

    def __init__(self) -> None:
        self.static: dict[tuple[str, str], np.ndarray] = {}
        self.dynamic: dict[tuple[str, str], tuple[list[float], list[np.ndarray]]] = {}

    def add(self, msg, static: bool) -> None:
        for tr in msg.transforms:
            key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            T = transform_matrix(tr.transform)
            if static:
                self.static[key] = T
            else:
                ts, Ts = self.dynamic.setdefault(key, ([], []))
                ts.append(stamp_seconds(tr.header.stamp))
                Ts.append(T)

    def frames(self) -> set[str]:
        return {f for k in [*self.static, *self.dynamic] for f in k}

    def path(self, parent: str, child: str) -> list[tuple[str, str, bool]] | None:
        """Edges from parent to child as (a, b, forward); None when the frames are not connected."""
        edges: dict[str, list[tuple[str, str, str, bool]]] = {}
        for a, b in [*self.static, *self.dynamic]:
            edges.setdefault(a, []).append((b, a, b, True))
            edges.setdefault(b, []).append((a, a, b, False))
        prev: dict[str, tuple[str, tuple[str, str, bool]] | None] = {parent: None}
        todo = deque([parent])
        while todo:
            f = todo.popleft()
            for nxt, a, b, fwd in edges.get(f, []):
                if nxt not in prev:
                    prev[nxt] = (f, (a, b, fwd))
                    todo.append(nxt)
        if child not in prev:
            return None
        out, f = [], child
        while prev[f] is not None:
            f, edge = prev[f]
            out.append(edge)
        return out[::-1]

    def lookup(self, path: list[tuple[str, str, bool]], t: float, max_dt: float) -> np.ndarray | None:
        """T_parent_child at time t (nearest sample of each dynamic edge within max_dt), or None."""
        T = np.eye(4)
        for a, b, fwd in path:
            E = self.static.get((a, b))
            if E is None:
                ts, Ts = self.dynamic[(a, b)]
                k = int(np.argmin(np.abs(np.asarray(ts) - t)))
                if abs(ts[k] - t) > max_dt:
                    return None
                E = Ts[k]
            T = T @ (E if fwd else np.linalg.inv(E))
        return T
