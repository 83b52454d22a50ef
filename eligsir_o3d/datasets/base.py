"""RGBDSequence: an indexable recorded RGB-D sequence, plus the parsing helpers every reader shares.

A reader (tum.py, replica.py, folder.py) only has to find its files, intrinsics, timestamps and poses and hand
them to :class:`RGBDSequence`; images are read lazily, one frame per ``seq[i]``, so opening a 1000-frame
sequence costs only the text parsing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import open3d as o3d

from ..core.camera import Camera, check_pose, pose_from_tum
from ..core.frame import DEPTH_MAX, Frame
from .errors import DatasetError
from .image_files import read_color, read_depth



@dataclass
class SequenceFrame:
    """One item of a sequence, as read from disk.

    rgbd: colour UInt8 [H, W, 3] RGB; depth UInt16 [H, W] raw sensor units (metres = value / depth_scale),
    or Float32 metres for in-memory sequences whose depth_scale is 1.0. T_world_cam: [4, 4] float64
    camera-to-world ground truth, or None when the sequence has none.
    """

    index: int
    timestamp: float
    rgbd: o3d.t.geometry.RGBDImage
    T_world_cam: np.ndarray | None
    color_path: Path | None = None
    depth_path: Path | None = None


class RGBDSequence:
    """A recorded RGB-D sequence: ``len(seq)``, ``seq[i] -> SequenceFrame``, ``seq.frame(i) -> Frame``.

    Attributes: name, path, camera (:class:`Camera`), intrinsic (Open3D), depth_scale (png value / depth_scale =
    metres), timestamps [N] float seconds (strictly increasing), poses (list of [4, 4] camera-to-world, or None),
    dropped_unassociated (frames of the source left out because no depth or pose matched them).

    Two cameras: ``camera`` is the depth camera's intrinsics; a reader that knows a separate colour camera passes
    ``color_camera`` (and ``T_color_depth``, ``poses_of``; see :mod:`.registration`). Each frame's depth is then
    registered into the colour camera as it is read, and ``seq.camera`` is the colour camera, the one camera
    everything downstream sees (``seq.depth_camera`` keeps the depth one, ``seq.rig`` the pair).
    """

    def __init__(self, *, name: str, path: Path | None, camera: Camera, depth_scale: float,
                 timestamps: Sequence[float], poses: list[np.ndarray] | None = None,
                 color_paths: Sequence[Path] = (), depth_paths: Sequence[Path] = (),
                 dropped_unassociated: int = 0, format: str = "", color_camera: Camera | None = None,
                 T_color_depth: np.ndarray | None = None, poses_of: str = "depth") -> None:
        self.name = name
        self.path = path
        self.format = format
        self.camera = camera
        self.depth_camera = camera
        self.rig = None
        self._depth_poses = None  # the given poses, when they were the depth camera's and got moved to the colour
        self.depth_scale = float(depth_scale)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.color_paths = [Path(p) for p in color_paths]
        self.depth_paths = [Path(p) for p in depth_paths]
        self.dropped_unassociated = int(dropped_unassociated)
        where = f"sequence {name!r}"
        n = len(self.timestamps)
        if n == 0:
            raise DatasetError(f"{where} ({path}): no frames (empty sequence)")
        if not self.depth_scale > 0:
            raise DatasetError(f"{where}: depth_scale must be positive, got {depth_scale}")
        if self.color_paths and (len(self.color_paths) != n or len(self.depth_paths) != n):
            raise DatasetError(f"{where}: {len(self.color_paths)} colour and {len(self.depth_paths)} depth files "
                               f"for {n} timestamps")
        nonfinite = np.flatnonzero(~np.isfinite(self.timestamps))
        if nonfinite.size:  # NaN passes every comparison below as false: a clock would never release the frame
            i = int(nonfinite[0])
            raise DatasetError(f"{where}: frame {i} has timestamp {self.timestamps[i]} (timestamps must be finite)")
        bad = np.flatnonzero(~(np.diff(self.timestamps) > 0))
        if bad.size:
            i = int(bad[0]) + 1
            raise DatasetError(f"{where}: timestamps must be strictly increasing; frame {i} has "
                               f"{self.timestamps[i]:.6f} after {self.timestamps[i - 1]:.6f}")
        if poses is not None:
            if len(poses) != n:
                raise DatasetError(f"{where}: {len(poses)} poses for {n} frames")
            checked = []
            for i, T in enumerate(poses):
                try:
                    checked.append(check_pose(T, f"{where}: pose of frame {i}"))
                except ValueError as e:
                    raise DatasetError(str(e)) from None
            poses = checked
        self.poses = poses
        if color_camera is not None:
            self._set_rig(color_camera, T_color_depth, poses_of)

    # -- two cameras ----------------------------------------------------------------------------------------
    def _set_rig(self, color_camera: Camera, T_color_depth: np.ndarray | None, poses_of: str) -> None:
        from .registration import TwoCameraRig

        try:
            rig = TwoCameraRig(self.depth_camera, color_camera, T_color_depth, poses_of)
        except ValueError as e:
            raise DatasetError(f"sequence {self.name!r}: colour camera: {e}") from None
        if rig.is_identity:
            return
        self.rig, self.camera = rig, rig.color
        if self.poses is not None and rig.poses_of == "depth" and not np.array_equal(rig.T_color_depth, np.eye(4)):
            self._depth_poses = self.poses
            self.poses = [rig.color_pose(T) for T in self.poses]

    def ignore_color_camera(self) -> None:
        """Use the depth camera for colour too, as if the sequence had one camera (no registration)."""
        if self.rig is None:
            return
        d, c = self.rig.depth, self.rig.color
        if (d.width, d.height) != (c.width, c.height):
            raise DatasetError(f"sequence {self.name!r}: colour images are {c.width}x{c.height} but depth images are "
                               f"{d.width}x{d.height}; the colour camera cannot be ignored")
        if self._depth_poses is not None:
            self.poses, self._depth_poses = self._depth_poses, None
        self.rig, self.camera = None, self.depth_camera

    def raw_images(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i as read, before registration: colour uint8 [H, W, 3] (colour camera), depth [h, w] raw units
        (depth camera)."""
        color, depth = self._read_images(self._index(int(i)))
        return color.as_tensor().numpy(), depth.as_tensor().numpy()[..., 0]

    # -- sizes and clocks ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[SequenceFrame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def intrinsic(self) -> o3d.camera.PinholeCameraIntrinsic:
        return self.camera.to_o3d()

    @property
    def frame_period_s(self) -> float:
        """Median spacing of the timestamps (1/30 s for a one-frame sequence)."""
        return float(np.median(np.diff(self.timestamps))) if len(self) > 1 else 1.0 / 30.0

    @property
    def acquisition_time_s(self) -> float:
        """How long the capture took: first to last timestamp plus one frame period."""
        return float(self.timestamps[-1] - self.timestamps[0]) + self.frame_period_s

    def __repr__(self) -> str:
        c = self.camera
        return (f"{type(self).__name__}(name={self.name!r}, format={self.format!r}, frames={len(self)}, "
                f"size={c.width}x{c.height}, fx={c.fx:g}, depth_scale={self.depth_scale:g}, "
                f"poses={'yes' if self.poses is not None else 'no'}"
                f"{'' if self.rig is None else f', depth registered from fx={self.depth_camera.fx:g}'})")

    # -- frames -------------------------------------------------------------------------------------------
    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for sequence {self.name!r} of {n} frames")
        return i % n

    def _read_images(self, i: int) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]:
        """(colour UInt8 [H, W, 3], depth [H, W, 1]) of frame i; file readers read from disk."""
        return (read_color(self.color_paths[i], i, self.camera),
                read_depth(self.depth_paths[i], i, self.depth_camera))

    def __getitem__(self, i: int) -> SequenceFrame:
        i = self._index(int(i))
        color, depth = self._read_images(i)
        if self.rig is not None:  # once, at read time: downstream sees one camera, the colour one
            try:
                registered = self.rig.register(depth.as_tensor().numpy(), self.depth_scale)
            except ValueError as e:
                raise DatasetError(f"frame {i}: cannot register depth into the colour camera: {e}") from None
            depth = o3d.t.geometry.Image(o3d.core.Tensor(registered[..., None]))
        pose = None if self.poses is None else self.poses[i].copy()
        return SequenceFrame(i, float(self.timestamps[i]), o3d.t.geometry.RGBDImage(color, depth, True), pose,
                             self.color_paths[i] if self.color_paths else None,
                             self.depth_paths[i] if self.depth_paths else None)

    def frame(self, i: int, depth_max: float = DEPTH_MAX, T_world_cam: np.ndarray | None = None) -> Frame:
        """Frame i as a :class:`Frame` (float colour, metric depth, capped at ``depth_max`` metres).

        Its pose is ``T_world_cam`` if given, else the ground truth; a sequence without poses gets the identity
        as a placeholder, for the caller's pose source to replace (``frame.T_world_cam = ...``).
        """
        item = self[i]
        T = item.T_world_cam if T_world_cam is None else T_world_cam
        return Frame.from_rgbd(item.rgbd, self.camera, np.eye(4) if T is None else T, depth_scale=self.depth_scale,
                               depth_max=depth_max, timestamp=item.timestamp, index=item.index)


# -- text files ---------------------------------------------------------------------------------------------
def read_table(path: Path, columns: int | tuple[int, ...], *, text_fields: int = 0,
               comment: str = "#") -> list[tuple[int, list[str]]]:
    """Rows of a whitespace (or comma) separated text file as (line number, fields), comments and blanks skipped.

    ``columns``: allowed field counts; all fields but the last ``text_fields`` must parse as finite floats.
    Raises DatasetError naming ``file:line`` for a malformed line.
    """
    allowed = (columns,) if isinstance(columns, int) else tuple(columns)
    from ..io.inputs import read_text

    try:  # a regular file, size-capped; a UTF-8 byte-order mark (Windows editors) is no field
        text = read_text(path, "text file", error=DatasetError)
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"cannot read {path}: {e}") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith(comment):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) not in allowed:
            want = " or ".join(str(c) for c in allowed)
            raise DatasetError(f"{path}:{lineno}: expected {want} fields, got {len(fields)}: {line[:80]!r}")
        for f in fields[:len(fields) - text_fields]:
            try:
                v = float(f)
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: {f!r} is not a number: {line[:80]!r}") from None
            if not np.isfinite(v):
                raise DatasetError(f"{path}:{lineno}: non-finite value {f!r}")
        rows.append((lineno, fields))
    return rows


def check_increasing(path: Path, linenos: Sequence[int], stamps: Sequence[float]) -> None:
    """Raise DatasetError naming ``file:line`` of the first timestamp that does not increase."""
    for k in range(1, len(stamps)):
        if not stamps[k] > stamps[k - 1]:
            raise DatasetError(f"{path}:{linenos[k]}: timestamp {stamps[k]:.6f} is not after the previous line's "
                               f"{stamps[k - 1]:.6f} (timestamps must be strictly increasing)")


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """TUM trajectory file ``timestamp tx ty tz qx qy qz qw`` -> (timestamps [N] float64, camera-to-world [4, 4]
    list): the package's one TUM reader, for ground truth and trajectory files alike.

    Each line holds 8 finite numbers with a non-zero quaternion, and timestamps increase strictly; a line that
    breaks the rule is a DatasetError (a ValueError) naming ``file:line``. A missing file is a FileNotFoundError,
    a file without poses a DatasetError.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} does not exist")
    rows = read_table(path, 8)
    if not rows:
        raise DatasetError(f"{path}: no poses (empty trajectory file)")
    stamps = [float(f[0]) for _, f in rows]
    check_increasing(path, [n for n, _ in rows], stamps)
    poses = []
    for lineno, f in rows:
        v = np.array(f[1:], dtype=np.float64)
        if np.linalg.norm(v[3:]) < 1e-6:
            raise DatasetError(f"{path}:{lineno}: zero quaternion")
        poses.append(pose_from_tum(v[:3], v[3:]))
    return np.array(stamps, dtype=np.float64), poses


def read_matrix_rows(path: Path) -> list[np.ndarray]:
    """One row-major 4x4 matrix per line (16 numbers), as in NICE-SLAM's traj.txt."""
    return [np.array(f, dtype=np.float64).reshape(4, 4) for _, f in read_table(path, 16)]


def read_matrix_file(path: Path) -> np.ndarray:
    """A 4x4 matrix written as 4 lines of 4 numbers (or one line of 16)."""
    rows = read_table(path, (4, 16))
    values = [float(x) for _, f in rows for x in f]
    if len(values) != 16:
        raise DatasetError(f"{path}: expected a 4x4 matrix (16 numbers), got {len(values)}")
    return np.array(values, dtype=np.float64).reshape(4, 4)


def read_intrinsics_json(path: Path) -> tuple[Camera, float | None]:
    """``intrinsics.json``: {width, height, fx, fy, cx, cy[, depth_scale]} -> (Camera, depth_scale or None)."""
    from ..io.inputs import read_json

    data = read_json(path, "intrinsics", error=DatasetError)
    if isinstance(data, dict) and isinstance(data.get("camera"), dict):
        data = data["camera"]
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if not isinstance(data, dict) or k not in data]
    if missing:
        raise DatasetError(f"{path}: missing field(s) {', '.join(missing)} "
                           f"(expected width, height, fx, fy, cx, cy and optionally depth_scale)")
    try:
        camera = Camera(int(data["width"]), int(data["height"]), float(data["fx"]), float(data["fy"]),
                        float(data["cx"]), float(data["cy"]))
        scale = float(data["depth_scale"]) if data.get("depth_scale") is not None else None
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{path}: bad intrinsics: {e}") from None
    if scale is not None and not scale > 0:
        raise DatasetError(f"{path}: depth_scale must be positive, got {scale}")
    return camera, scale


def read_color_sidecar(path: Path, depth_camera: Camera) -> dict:
    """Keyword arguments for :class:`RGBDSequence` (``color_camera``, ``T_color_depth``, ``poses_of``) from the
    optional ``color`` block of an ``intrinsics.json`` sidecar (see :mod:`.registration`); {} without one."""
    from .registration import read_color_block

    try:
        rig = read_color_block(path, depth_camera)
    except ValueError as e:
        raise DatasetError(str(e)) from None
    if rig is None:
        return {}
    return {"color_camera": rig.color, "T_color_depth": rig.T_color_depth, "poses_of": rig.poses_of}
