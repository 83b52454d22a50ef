"""ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``, sqlite3 ``.db3`` or ``.mcap``) bags, via ``rosbags``.

Reads colour (``sensor_msgs/Image`` rgb8/bgr8/rgba8/bgra8/mono8 or ``CompressedImage``), depth (``16UC1``/``mono16``
millimetres or ``32FC1`` metres), ``CameraInfo`` and, when present, poses: ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped``, ``nav_msgs/Odometry`` on a topic, or ``tf`` between two named frames
(``pose_frames="world:camera_color_optical_frame"``). Poses are of the camera's optical frame (OpenCV axes).

Topics are found by message type (and image encoding) when there is one candidate; otherwise the error lists the
candidates and the option to choose with: ``rgb_topic``, ``depth_topic``, ``rgb_info_topic``, ``depth_info_topic``,
``pose_topic`` (CLI: ``--rgb-topic`` ...). A depth topic with ``aligned`` in its name wins over other depth topics
(the RealSense ROS driver's ``aligned_depth_to_color``). Colour and depth are paired by nearest header stamp
within ``max_dt`` (default 0.02 s), one-to-one as for TUM, and each pair gets the nearest pose within ``max_dt``;
unpaired colour frames are dropped with a warning. Opening reads the bag once for stamps (images are not
decoded); ``seq[i]`` then reads that frame's two messages by their bag time, so memory stays flat however long
the bag. Without CameraInfo pass ``intrinsics="path/to/intrinsics.json"``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import open3d as o3d

from .base import DatasetError, RGBDSequence, read_intrinsics_json
from .rosmsg import (COLOR_ENCODINGS, COMPRESSED_TYPE, DEPTH_ENCODINGS, IMAGE_TYPE, INFO_TYPE, POSE_TYPES, TF_TYPE,
                     TfBuffer, camera_from_info, color_from_msg, depth_from_msg, header_stamp, import_rosbags,
                     pose_from_msg, stamp_seconds)
from .tum import associate, nearest
from .twocam import TwoCameras, combine

ROS2_SUFFIXES = (".mcap", ".db3")


def detect(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() in (".bag", *ROS2_SUFFIXES)
    return path.is_dir() and (path / "metadata.yaml").is_file()


def open_reader(path: Path):
    """An opened rosbags AnyReader; DatasetError naming the file when the bag cannot be read."""
    rb = import_rosbags()
    try:
        reader = rb.AnyReader([path], default_typestore=rb.get_typestore(rb.Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises several unrelated types for damaged files
        raise DatasetError(f"{path}: cannot read the bag ({type(e).__name__}: {e}); is it truncated, still being "
                           f"recorded, or not a ROS bag?") from None
    return reader


class BagSequence(RGBDSequence):
    """An RGBDSequence whose frames are read from a bag on demand (one colour and one depth message each)."""

    def __init__(self, *, reader, color_ref: list[tuple[object, int]], depth_ref: list[tuple[object, int]],
                 cameras: TwoCameras, topics: dict, **kwargs) -> None:
        super().__init__(**cameras.sequence_kwargs("color"), **kwargs)
        self._reader = reader
        self._color_ref, self._depth_ref = color_ref, depth_ref  # per frame: (connection, bag time ns)
        self.cameras = cameras
        self.color_intrinsic, self.depth_intrinsic = cameras.color_intrinsic, cameras.depth_intrinsic
        self.T_color_depth = cameras.T_color_depth
        self.topics = topics

    def _message(self, ref: tuple[object, int], i: int, what: str):
        conn, t_ns = ref
        try:
            for c, _, raw in self._reader.messages(connections=[conn], start=t_ns, stop=t_ns + 1):
                return self._reader.deserialize(raw, c.msgtype)
        except Exception as e:
            raise DatasetError(f"frame {i}: cannot read the {what} message at t={t_ns * 1e-9:.6f} from "
                               f"{self.path}: {e}") from None
        raise DatasetError(f"frame {i}: the {what} message at t={t_ns * 1e-9:.6f} is missing from {self.path}")

    def read_native(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i's colour [Hc, Wc, 3] uint8 and depth [Hd, Wd] (uint16 mm or float32 m) as recorded."""
        i = self._index(int(i))
        cconn = self._color_ref[i][0]
        color = color_from_msg(self._message(self._color_ref[i], i, "colour"), cconn.msgtype,
                               f"frame {i} ({self.path} {cconn.topic})")
        depth = depth_from_msg(self._message(self._depth_ref[i], i, "depth"),
                               f"frame {i} ({self.path} {self._depth_ref[i][0].topic})")
        return color, depth

    def _read_images(self, i: int) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]:
        color, depth = combine(*self.read_native(i), self.cameras)
        return o3d.t.geometry.Image(o3d.core.Tensor(color)), o3d.t.geometry.Image(o3d.core.Tensor(depth[..., None]))

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def _choose(kind: str, candidates: list[tuple[str, str]], given: str | None, option: str, path: Path,
            topics: dict[str, str], required: bool = True) -> str | None:
    if given is not None:
        if given not in topics:
            raise DatasetError(f"{path}: no topic {given!r} ({option}); the bag has: {', '.join(sorted(topics))}")
        return given
    if len(candidates) == 1:
        return candidates[0][0]
    if not candidates:
        if required:
            raise DatasetError(f"{path}: no {kind} topic found; the bag has: "
                               f"{', '.join(f'{t} ({m})' for t, m in sorted(topics.items())) or 'no topics'}")
        return None
    listed = ", ".join(f"{t} ({d})" for t, d in candidates)
    raise DatasetError(f"{path}: {len(candidates)} candidate {kind} topics: {listed}; choose one with "
                       f"--{option.replace('_', '-')} (option {option}=...)")


def _first(reader, conn):
    for c, _, raw in reader.messages(connections=[conn]):
        return reader.deserialize(raw, c.msgtype)
    return None


def _pick_topics(reader, conns: dict, topics: dict, path: Path, rgb_topic, depth_topic, rgb_info_topic,
                 depth_info_topic, pose_topic, pose_frames):
    """(colour, depth, colour CameraInfo, depth CameraInfo, pose) topics: the given ones, checked, else the only
    candidate of each kind (an ambiguous or missing choice is a DatasetError that lists the candidates)."""
    colors, depths, unsupported = [], [], []
    for t, typ in sorted(topics.items()):
        if typ == COMPRESSED_TYPE:
            (depths if "depth" in t.lower() else colors).append((t, "CompressedImage"))
        elif typ == IMAGE_TYPE:
            first = _first(reader, conns[t][0])
            enc = getattr(first, "encoding", "?")
            if enc in COLOR_ENCODINGS:
                colors.append((t, f"Image {enc}"))
            elif enc in DEPTH_ENCODINGS or "depth" in t.lower():
                depths.append((t, f"Image {enc}"))
            else:
                unsupported.append(f"{t} (Image {enc})")
    if not colors and rgb_topic is None and unsupported:  # say why the image topic there is not taken
        raise DatasetError(f"{path}: no colour image topic with a supported encoding "
                           f"({', '.join(sorted(COLOR_ENCODINGS))}); the bag's image topic(s) "
                           f"{', '.join(unsupported)} have another encoding")
    aligned = [c for c in depths if "aligned" in c[0]]
    if depth_topic is None and len(aligned) == 1:
        depths = aligned
    rgb_topic = _choose("colour image", colors, rgb_topic, "rgb_topic", path, topics)
    depth_topic = _choose("depth image", depths, depth_topic, "depth_topic", path, topics)
    if topics[depth_topic] == COMPRESSED_TYPE:
        raise DatasetError(f"{path}: depth topic {depth_topic} is a CompressedImage (compressedDepth); only raw "
                           f"Image depth (16UC1, mono16, 32FC1) is supported")
    infos = sorted(t for t, typ in topics.items() if typ == INFO_TYPE)

    def info_for(image_topic: str, given: str | None, option: str) -> str | None:
        if given is not None:
            return _choose("CameraInfo", [], given, option, path, topics)
        sibling = image_topic.rsplit("/", 1)[0] + "/camera_info"
        base = image_topic.rsplit("/compressed", 1)[0].rsplit("/", 1)[0] + "/camera_info"
        for cand in (sibling, base):
            if cand in infos:
                return cand
        return infos[0] if len(infos) == 1 else None

    rgb_info = info_for(rgb_topic, rgb_info_topic, "rgb_info_topic")
    depth_info = info_for(depth_topic, depth_info_topic, "depth_info_topic")
    if pose_frames is None:
        poses_c = [(t, typ.split("/")[-1]) for t, typ in sorted(topics.items()) if typ in POSE_TYPES]
        pose_topic = _choose("pose", poses_c, pose_topic, "pose_topic", path, topics, required=False)
    elif pose_topic is not None:
        raise DatasetError("give pose_topic or pose_frames, not both")

    return rgb_topic, depth_topic, rgb_info, depth_info, pose_topic


def _read_messages(reader, conns: dict, topics: dict, path: Path, ros1: bool, rgb_topic, depth_topic, rgb_info,
                   depth_info, pose_topic, pose_frames):
    """One pass over the bag: per image topic its header stamps and message refs, the first CameraInfo of each info
    topic, the pose messages (stamps, T_world_cam) and the tf tree."""
    want = {rgb_topic, depth_topic, *(t for t in (rgb_info, depth_info, pose_topic) if t)}
    if pose_frames is not None:
        want |= {t for t, typ in topics.items() if typ == TF_TYPE}
    stamps: dict[str, tuple[list[float], list]] = {rgb_topic: ([], []), depth_topic: ([], [])}
    info_msgs: dict[str, object] = {}
    pose_t, pose_T = [], []
    tf = TfBuffer()
    try:
        for c, t_ns, raw in reader.messages(connections=[c for t in want for c in conns[t]]):
            if c.topic in stamps:
                stamps[c.topic][0].append(header_stamp(raw, ros1))
                stamps[c.topic][1].append((c, t_ns))
            elif c.topic in (rgb_info, depth_info):
                if c.topic not in info_msgs:
                    info_msgs[c.topic] = reader.deserialize(raw, c.msgtype)
            elif c.topic == pose_topic:
                msg = reader.deserialize(raw, c.msgtype)
                pose_t.append(stamp_seconds(msg.header.stamp))
                pose_T.append(pose_from_msg(msg, c.msgtype))
            else:  # tf
                tf.add(reader.deserialize(raw, c.msgtype), static="static" in c.topic)
    except DatasetError as e:
        raise DatasetError(f"{path}: {e}") from None
    except Exception as e:
        raise DatasetError(f"{path}: cannot read the bag's messages ({type(e).__name__}: {e}); is it truncated?") \
            from None
    if not stamps[depth_topic][0]:
        raise DatasetError(f"{path}: depth topic {depth_topic} has no messages")
    if not stamps[rgb_topic][0]:
        raise DatasetError(f"{path}: colour topic {rgb_topic} has no messages")

    return stamps, info_msgs, pose_t, pose_T, tf


def open_rosbag(path: Path, *, rgb_topic: str | None = None, depth_topic: str | None = None,
                rgb_info_topic: str | None = None, depth_info_topic: str | None = None,
                pose_topic: str | None = None, pose_frames: str | None = None, max_dt: float = 0.02,
                intrinsics: str | None = None, depth_scale: float | None = None) -> BagSequence:
    """Open a ROS 1 or ROS 2 bag (see the module docstring for the rules and options)."""
    if not max_dt > 0:
        raise DatasetError(f"max_dt must be positive, got {max_dt}")
    reader = open_reader(path)
    ros1 = not reader.is2
    conns: dict[str, list] = {}
    for c in reader.connections:
        conns.setdefault(c.topic, []).append(c)
    topics = {t: cs[0].msgtype for t, cs in conns.items()}

    rgb_topic, depth_topic, rgb_info, depth_info, pose_topic = _pick_topics(
        reader, conns, topics, path, rgb_topic, depth_topic, rgb_info_topic, depth_info_topic, pose_topic, pose_frames)

    stamps, info_msgs, pose_t, pose_T, tf = _read_messages(reader, conns, topics, path, ros1, rgb_topic, depth_topic,
                                                           rgb_info, depth_info, pose_topic, pose_frames)

    # -- cameras ---------------------------------------------------------------------------------------------------
    first_depth = depth_from_msg(reader.deserialize(*_raw_first(reader, stamps[depth_topic][1][0])),
                                 f"{path} {depth_topic}")
    if intrinsics is not None:
        cam, scale = read_intrinsics_json(Path(intrinsics))
        ccam = dcam = cam
    else:
        if rgb_info is None and depth_info is None:
            raise DatasetError(f"{path}: no CameraInfo topic for {rgb_topic} or {depth_topic}; pass "
                               f"intrinsics=path/to/intrinsics.json (width, height, fx, fy, cx, cy)")
        scale = None
        ccam = camera_from_info(info_msgs[rgb_info or depth_info], f"{path} {rgb_info or depth_info}")
        dcam = camera_from_info(info_msgs[depth_info or rgb_info], f"{path} {depth_info or rgb_info}")
    if first_depth.shape != (dcam.height, dcam.width):
        raise DatasetError(f"{path}: depth images on {depth_topic} are {first_depth.shape[1]}x{first_depth.shape[0]} "
                           f"but its CameraInfo says {dcam.width}x{dcam.height}")
    registered = ccam == dcam or "aligned" in depth_topic
    cameras = TwoCameras(ccam, ccam if registered else dcam, _extrinsic(tf, info_msgs, rgb_info, depth_info, max_dt),
                         registered)
    if not registered:
        warnings.warn(f"{path.name}: colour ({ccam.width}x{ccam.height}, fx={ccam.fx:g}) and depth "
                      f"({dcam.width}x{dcam.height}, fx={dcam.fx:g}) cameras differ; depth is registered into the colour "
                      f"camera as frames are read", stacklevel=3)

    # -- association -------------------------------------------------------------------------------------------------
    rgb_t, rgb_ref = np.asarray(stamps[rgb_topic][0]), stamps[rgb_topic][1]
    d_t, d_ref = np.asarray(stamps[depth_topic][0]), stamps[depth_topic][1]
    pairs = associate(rgb_t, d_t, max_dt)
    no_depth, no_pose, poses = len(rgb_t) - len(pairs), 0, None
    if pose_topic is not None or pose_frames is not None:
        Ts = _poses_at(rgb_t[[i for i, _ in pairs]], pose_t, pose_T, tf, pose_frames, max_dt, path)
        no_pose = sum(T is None for T in Ts)
        pairs = [p for p, T in zip(pairs, Ts) if T is not None]
        poses = [T for T in Ts if T is not None]
    if not pairs:
        raise DatasetError(f"{path}: no frame left after pairing {rgb_topic} with {depth_topic}"
                           f"{' and poses' if poses is not None else ''} within max_dt={max_dt} s")
    dropped = no_depth + no_pose
    if dropped:
        warnings.warn(f"{path.name}: dropped {dropped} of {len(rgb_t)} colour frames ({no_depth} without depth, "
                      f"{no_pose} without a pose within {max_dt} s)", stacklevel=3)
    if depth_scale is None:
        depth_scale = 1.0 if first_depth.dtype == np.float32 else (scale or 1000.0)
    seq = BagSequence(reader=reader, color_ref=[rgb_ref[i] for i, _ in pairs], depth_ref=[d_ref[j] for _, j in pairs],
                      cameras=cameras, name=path.resolve().stem, path=path, depth_scale=depth_scale,
                      timestamps=rgb_t[[i for i, _ in pairs]], poses=poses, dropped_unassociated=dropped,
                      format="ros1" if ros1 else "ros2",
                      topics={"rgb": rgb_topic, "depth": depth_topic, "rgb_info": rgb_info, "depth_info": depth_info,
                              "pose": pose_topic, "pose_frames": pose_frames})
    seq.default_pose = "odometry"
    return seq


def _raw_first(reader, ref) -> tuple[bytes, str]:
    conn, t_ns = ref
    for c, _, raw in reader.messages(connections=[conn], start=t_ns, stop=t_ns + 1):
        return raw, c.msgtype
    raise DatasetError(f"message at {t_ns} vanished")


def _poses_at(stamps: np.ndarray, pose_t: list, pose_T: list, tf: TfBuffer, pose_frames: str | None,
              max_dt: float, path: Path) -> list:
    if pose_frames is None:
        if not pose_t:
            return [None] * len(stamps)
        order = np.argsort(pose_t)
        k = nearest(np.asarray(pose_t)[order], stamps, max_dt)
        return [pose_T[order[kk]] if kk >= 0 else None for kk in k]
    parent, _, child = pose_frames.partition(":")
    chain = tf.path(parent.strip("/"), child.strip("/"))
    if not child or chain is None:
        raise DatasetError(f"{path}: no tf chain from {parent!r} to {child!r} (pose_frames='parent:child'); "
                           f"tf frames in the bag: {', '.join(sorted(tf.frames())) or 'none'}")
    return [tf.lookup(chain, t, max_dt) for t in stamps]


def _extrinsic(tf: TfBuffer, infos: dict, rgb_info: str | None, depth_info: str | None, max_dt: float):
    """T_color_depth from tf between the two CameraInfo frame ids, when the bag's tf connects them."""
    if not (rgb_info and depth_info and tf.frames()):
        return None
    a, b = (infos[t].header.frame_id.lstrip("/") for t in (rgb_info, depth_info))
    chain = tf.path(a, b)
    return None if chain is None else tf.lookup(chain, 0.0, float("inf"))
