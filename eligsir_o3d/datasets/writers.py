"""Write an RGB-D sequence as a ROS 1 bag, a ROS 2 bag (sqlite3 or mcap) or a ScanNet ``.sens`` file.

The readers of those formats (rosbag.py, scannet.py, rsbag.py) are tested by writing real frames with these
functions and reading them back; users can use them to hand a recording to ROS tools. Frames are written one at
a time (memory stays at one frame). Bags need ``rosbags`` (``pip install 'eligsir-o3d[bags]'``).

Topics of a written ROS bag (``topics=`` renames them): ``/camera/color/image_raw`` (``sensor_msgs/Image`` rgb8,
or ``.../compressed`` ``CompressedImage`` JPEG with ``color="jpeg"``), ``/camera/depth/image_raw`` (``16UC1``
millimetres or ``32FC1`` metres), ``/camera/color/camera_info`` and ``/camera/depth/camera_info``, and the
ground-truth poses as ``geometry_msgs/PoseStamped`` (``poses="pose"``), ``nav_msgs/Odometry`` (``"odometry"``) or
``/tf`` ``world -> camera_link`` plus a static ``camera_link -> camera_color_optical_frame`` (``"tf"``).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import Camera
from ..core.camera import pose_to_tum
from .rosmsg import import_rosbags

DEFAULT_TOPICS = {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_raw",
                  "rgb_info": "/camera/color/camera_info", "depth_info": "/camera/depth/camera_info",
                  "pose": "/camera/pose", "tf": "/tf", "tf_static": "/tf_static"}
COLOR_FRAME = "camera_color_optical_frame"
DEPTH_FRAME = "camera_depth_optical_frame"
# camera_link -> optical frame: any fixed rotation works for the tests; this is the REP-103 body-to-optical one.
T_LINK_OPTICAL = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def _frames(seq, frames: Sequence[int] | None) -> list[int]:
    return list(range(len(seq))) if frames is None else [int(i) for i in frames]


class _Msgs:
    """Message builders for one typestore (ROS 1 and ROS 2 spell some fields differently)."""

    def __init__(self, ros: int) -> None:
        rb = import_rosbags()
        self.ros = ros
        self.ts = rb.get_typestore(rb.Stores.ROS1_NOETIC if ros == 1 else rb.Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:
            self.ts.register(rb.get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types

    def serialize(self, msg, msgtype: str) -> bytes:
        return self.ts.serialize_ros1(msg, msgtype) if self.ros == 1 else self.ts.serialize_cdr(msg, msgtype)

    def header(self, t_ns: int, frame_id: str, seq: int = 0):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if self.ros == 1:
            return self.T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def image(self, t_ns: int, frame_id: str, a: np.ndarray, encoding: str):
        a = np.ascontiguousarray(a)
        h, w = a.shape[:2]
        return self.T["sensor_msgs/msg/Image"](header=self.header(t_ns, frame_id), height=h, width=w,
                                               encoding=encoding, is_bigendian=0, step=a.strides[0],
                                               data=a.reshape(-1).view(np.uint8))

    def compressed(self, t_ns: int, frame_id: str, data: bytes, fmt: str):
        return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(t_ns, frame_id), format=fmt,
                                                         data=np.frombuffer(data, dtype=np.uint8))

    def camera_info(self, t_ns: int, frame_id: str, cam: Camera):
        K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], dtype=np.float64)
        P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0], dtype=np.float64)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if self.ros == 1 else ("d", "k", "r", "p")
        arrays = dict(zip(names, (np.zeros(5), K, np.eye(3).reshape(-1), P)))
        return self.T["sensor_msgs/msg/CameraInfo"](header=self.header(t_ns, frame_id), height=cam.height,
                                                    width=cam.width, distortion_model="plumb_bob", binning_x=0,
                                                    binning_y=0, roi=roi, **arrays)

    def pose(self, T: np.ndarray):
        t, q = pose_to_tum(T)
        return self.T["geometry_msgs/msg/Pose"](position=self.T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
                                                orientation=self.T["geometry_msgs/msg/Quaternion"](
                                                    x=q[0], y=q[1], z=q[2], w=q[3]))

    def transform(self, t_ns: int, parent: str, child: str, T: np.ndarray):
        p = self.pose(T)
        tr = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
            rotation=p.orientation)
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t_ns, parent), child_frame_id=child,
                                                            transform=tr)

    def odometry(self, t_ns: int, parent: str, child: str, T: np.ndarray):
        cov = np.zeros(36)
        zero = self.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return self.T["nav_msgs/msg/Odometry"](
            header=self.header(t_ns, parent), child_frame_id=child,
            pose=self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(T), covariance=cov),
            twist=self.T["geometry_msgs/msg/TwistWithCovariance"](
                twist=self.T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov))


def write_rosbag(seq, out: str | Path, *, ros: int = 1, storage: str = "sqlite3", frames: Sequence[int] | None = None,
                 color: str = "raw", depth: str = "16UC1", poses: str | None = "pose", topics: dict | None = None,
                 depth_camera: Camera | None = None, t0: float = 1.7e9, write_depth: bool = True,
                 extra_topics: Sequence[str] = (), color_encoding: str = "rgb8") -> Path:
    """Write frames of ``seq`` (an RGBDSequence) as a ROS 1 ``.bag`` (``ros=1``) or a ROS 2 bag folder.

    color: "raw" (rgb8 Image) or "jpeg" (CompressedImage; the source JPEG bytes when the frame comes from a
    .jpg file). depth: "16UC1" (mm) or "32FC1" (m) or any other encoding string (written as 16UC1 data under
    that name, to test the reader's refusal). poses: "pose" | "odometry" | "tf" | None. depth_camera: the depth
    camera's CameraInfo (default: ``seq.camera`` for both). t0: added to the sequence's timestamps (ROS time).
    extra_topics: more colour topics carrying the same images (to make topic choice ambiguous). color_encoding:
    the raw colour images' encoding name (rgb8 data under another name, to test the reader's refusal).
    """
    rb = import_rosbags()
    out = Path(out)
    topics = {**DEFAULT_TOPICS, **(topics or {})}
    if color == "jpeg" and not topics["rgb"].endswith("compressed"):
        topics["rgb"] += "/compressed"
    m = _Msgs(ros)
    if ros == 1:
        writer = rb.Writer1(out)
        add = lambda topic, typ: writer.add_connection(topic, typ, typestore=m.ts)  # noqa: E731
    else:
        plugin = {"sqlite3": rb.StoragePlugin.SQLITE3, "mcap": rb.StoragePlugin.MCAP}[storage]
        writer = rb.Writer2(out, version=8, storage_plugin=plugin)
        add = lambda topic, typ: writer.add_connection(topic, typ, typestore=m.ts)  # noqa: E731
    img_type = "sensor_msgs/msg/CompressedImage" if color == "jpeg" else "sensor_msgs/msg/Image"
    with writer:
        c_rgb = [add(t, img_type) for t in (topics["rgb"], *extra_topics)]
        c_depth = add(topics["depth"], "sensor_msgs/msg/Image") if write_depth else None
        c_info = add(topics["rgb_info"], "sensor_msgs/msg/CameraInfo")
        c_dinfo = add(topics["depth_info"], "sensor_msgs/msg/CameraInfo") if write_depth else None
        c_pose = None
        if poses == "pose":
            c_pose = (add(topics["pose"], "geometry_msgs/msg/PoseStamped"), "geometry_msgs/msg/PoseStamped")
        elif poses == "odometry":
            c_pose = (add(topics["pose"], "nav_msgs/msg/Odometry"), "nav_msgs/msg/Odometry")
        elif poses == "tf":
            c_pose = (add(topics["tf"], "tf2_msgs/msg/TFMessage"), "tf2_msgs/msg/TFMessage")
            c_static = add(topics["tf_static"], "tf2_msgs/msg/TFMessage")
        for k, i in enumerate(_frames(seq, frames)):
            item = seq[i]
            t_ns = int(round((t0 + item.timestamp) * 1e9))
            if k == 0 and poses == "tf":
                static = m.T["tf2_msgs/msg/TFMessage"](transforms=[
                    m.transform(t_ns, "camera_link", COLOR_FRAME, T_LINK_OPTICAL)])
                writer.write(c_static, t_ns, m.serialize(static, "tf2_msgs/msg/TFMessage"))
            rgb = item.rgbd.color.as_tensor().numpy()
            if color == "jpeg":
                msg = m.compressed(t_ns, COLOR_FRAME, _jpeg_bytes(item, rgb), "jpeg")
            else:
                msg = m.image(t_ns, COLOR_FRAME, rgb, color_encoding)
            for c in c_rgb:
                writer.write(c, t_ns, m.serialize(msg, img_type))
            writer.write(c_info, t_ns, m.serialize(m.camera_info(t_ns, COLOR_FRAME, seq.camera),
                                                   "sensor_msgs/msg/CameraInfo"))
            if write_depth:
                d = item.rgbd.depth.as_tensor().numpy()[..., 0]
                if depth == "32FC1":
                    dm = d.astype(np.float32) / np.float32(seq.depth_scale)
                    dm[d == 0] = np.nan  # ROS convention for "no measurement" in float depth
                    dmsg = m.image(t_ns, DEPTH_FRAME, dm, "32FC1")
                else:
                    mm = np.round(d.astype(np.float64) * (1000.0 / seq.depth_scale)).astype(np.uint16)
                    dmsg = m.image(t_ns, DEPTH_FRAME, mm, depth)
                writer.write(c_depth, t_ns, m.serialize(dmsg, "sensor_msgs/msg/Image"))
                writer.write(c_dinfo, t_ns, m.serialize(m.camera_info(t_ns, DEPTH_FRAME, depth_camera or seq.camera),
                                                        "sensor_msgs/msg/CameraInfo"))
            if c_pose is not None and item.T_world_cam is not None:
                conn, typ = c_pose
                T = item.T_world_cam
                if poses == "pose":
                    msg = m.T[typ](header=m.header(t_ns, "world"), pose=m.pose(T))
                elif poses == "odometry":
                    msg = m.odometry(t_ns, "world", COLOR_FRAME, T)
                else:
                    msg = m.T[typ](transforms=[m.transform(t_ns, "world", "camera_link",
                                                           T @ np.linalg.inv(T_LINK_OPTICAL))])
                writer.write(conn, t_ns, m.serialize(msg, typ))
    return out


def _jpeg_bytes(item, rgb: np.ndarray) -> bytes:
    if item.color_path is not None and item.color_path.suffix.lower() in (".jpg", ".jpeg"):
        return item.color_path.read_bytes()
    import cv2

    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise ValueError("cannot JPEG-encode a colour frame")
    return buf.tobytes()


# -- ScanNet .sens ---------------------------------------------------------------------------------------------
def write_sens(seq, out: str | Path, *, frames: Sequence[int] | None = None, version: int = 4,
               color_camera: Camera | None = None, color_size: tuple[int, int] | None = None,
               bad_pose_frames: Sequence[int] = (), sensor_name: str = "eligsir") -> Path:
    """Write frames of ``seq`` as a ScanNet ``.sens`` file (JPEG colour, zlib uint16 depth in mm, poses).

    color_size: (width, height) to resize the colour to (ScanNet's colour camera is 1296x968, its depth 640x480);
    color_camera: the colour intrinsics (default: ``seq.camera`` scaled to ``color_size``). bad_pose_frames: frame
    positions whose pose is written as -inf, as ScanNet does where its tracking failed.
    """
    import cv2

    out = Path(out)
    idx = _frames(seq, frames)
    cam = seq.camera
    cw, ch = color_size or (cam.width, cam.height)
    ccam = color_camera or Camera(cw, ch, cam.fx * cw / cam.width, cam.fy * ch / cam.height,
                                  cam.cx * cw / cam.width, cam.cy * ch / cam.height)

    def K(c: Camera) -> bytes:
        M = np.array([[c.fx, 0, c.cx, 0], [0, c.fy, c.cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float32)
        return M.tobytes()

    with open(out, "wb") as f:
        name = sensor_name.encode()
        f.write(struct.pack("<IQ", version, len(name)) + name)
        f.write(K(ccam) + np.eye(4, dtype=np.float32).tobytes() + K(cam) + np.eye(4, dtype=np.float32).tobytes())
        f.write(struct.pack("<ii", 2, 1))  # colour: JPEG; depth: zlib_ushort
        f.write(struct.pack("<IIIIfQ", cw, ch, cam.width, cam.height, 1000.0, len(idx)))
        for k, i in enumerate(idx):
            item = seq[i]
            T = np.full((4, 4), -np.inf, np.float32) if k in set(bad_pose_frames) or item.T_world_cam is None \
                else item.T_world_cam.astype(np.float32)
            rgb = item.rgbd.color.as_tensor().numpy()
            if color_size is None and item.color_path is not None and item.color_path.suffix.lower() in (".jpg",
                                                                                                      ".jpeg"):
                jpg = item.color_path.read_bytes()
            else:
                img = cv2.resize(rgb, (cw, ch), interpolation=cv2.INTER_LINEAR) if (cw, ch) != (cam.width, cam.height) \
                    else rgb
                jpg = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
            d = item.rgbd.depth.as_tensor().numpy()[..., 0]
            mm = np.round(d.astype(np.float64) * (1000.0 / seq.depth_scale)).astype("<u2")
            z = zlib.compress(mm.tobytes(), 1)
            t_us = int(round(item.timestamp * 1e6))
            f.write(T.tobytes() + struct.pack("<QQQQ", t_us, t_us, len(jpg), len(z)) + jpg + z)
    return out


# -- RealSense (librealsense ROS 1 layout, file version 3) ------------------------------------------------------
RS_DEPTH = "/device_0/sensor_0/Depth_0"
RS_COLOR = "/device_0/sensor_1/Color_0"


def write_realsense_bag(seq, out: str | Path, *, frames: Sequence[int] | None = None, depth_units: float = 0.001,
                        t0: float = 1.0, poses: bool = False) -> Path:
    """Write frames of ``seq`` in the layout librealsense records (``rs-record``, RealSense Viewer): file version 3,
    a "Stereo Module" sensor with a Z16 ``Depth_0`` stream and an "RGB Camera" sensor with an RGB8 ``Color_0``
    stream, each with its StreamInfo, CameraInfo and extrinsic, and the ``Depth Units`` option.
    Depth is written in ``depth_units`` metres per unit; both streams use ``seq.camera``. poses: also write the
    ground truth as ``geometry_msgs/PoseStamped`` on ``/camera/pose`` (not part of librealsense's layout; it ignores it).
    """
    rb = import_rosbags()
    out = Path(out)
    m = _Msgs(1)
    if "realsense_msgs/msg/StreamInfo" not in m.ts.types:
        m.ts.register(rb.get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended",
                                            "realsense_msgs/msg/StreamInfo"))
    T = m.T
    idx = _frames(seq, frames)
    fps = int(round(1.0 / seq.frame_period_s)) if len(seq) > 1 else 30
    writer = rb.Writer1(out)
    with writer:
        conns: dict[str, object] = {}

        def put(topic: str, typ: str, msg, t_ns: int = 1) -> None:  # static info at t = 1 ns (0 is invalid)
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=m.ts)
            writer.write(conns[topic], t_ns, m.serialize(msg, typ))

        kv = lambda k, v: T["diagnostic_msgs/msg/KeyValue"](key=k, value=v)  # noqa: E731
        put("/file_version", "std_msgs/msg/UInt32", T["std_msgs/msg/UInt32"](data=3))
        for k, v in (("Name", "Intel RealSense D435"), ("Serial Number", "000000000000"),
                     ("Firmware Version", "05.13.00.50"), ("Product Id", "0B07"), ("Product Line", "D400")):
            put("/device_0/info", "diagnostic_msgs/msg/KeyValue", kv(k, v))
        put("/device_0/sensor_0/info", "diagnostic_msgs/msg/KeyValue", kv("Name", "Stereo Module"))
        put("/device_0/sensor_1/info", "diagnostic_msgs/msg/KeyValue", kv("Name", "RGB Camera"))
        put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32",
            T["std_msgs/msg/Float32"](data=depth_units))
        put("/device_0/sensor_0/option/Depth Units/description", "std_msgs/msg/String",
            T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))
        ident = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                 rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
        for stream, enc in ((RS_DEPTH, "mono16"), (RS_COLOR, "rgb8")):
            put(f"{stream}/info", "realsense_msgs/msg/StreamInfo",
                T["realsense_msgs/msg/StreamInfo"](fps=fps, encoding=enc, is_recommended=True))
            put(f"{stream}/info/camera_info", "sensor_msgs/msg/CameraInfo", m.camera_info(0, "0", seq.camera))
            put(f"{stream}/tf/0", "geometry_msgs/msg/Transform", ident)
        for k, i in enumerate(idx):
            item = seq[i]
            t_ns = int(round((t0 + item.timestamp) * 1e9))
            d = item.rgbd.depth.as_tensor().numpy()[..., 0].astype(np.float64) / seq.depth_scale
            units = np.round(d / depth_units).astype(np.uint16)
            for stream, img, enc in ((RS_DEPTH, units, "mono16"), (RS_COLOR, item.rgbd.color.as_tensor().numpy(),
                                                                    "rgb8")):
                msg = m.image(t_ns, "0", img, enc)
                msg.header.seq = k
                put(f"{stream}/image/data", "sensor_msgs/msg/Image", msg, t_ns)
                for key, val in (("frame_timestamp", f"{(t0 + item.timestamp) * 1e3:.6f}"),
                                 ("timestamp_domain", "System Time"), ("system_time", str(t_ns // 1000000))):
                    put(f"{stream}/image/metadata", "diagnostic_msgs/msg/KeyValue", kv(key, val), t_ns)
            if poses and item.T_world_cam is not None:
                put("/camera/pose", "geometry_msgs/msg/PoseStamped",
                    T["geometry_msgs/msg/PoseStamped"](header=m.header(t_ns, "world"), pose=m.pose(item.T_world_cam)),
                    t_ns)
    return out
