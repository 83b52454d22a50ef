"""Two cameras, one frame: depth registered into the colour camera at read time.

Many recordings come from a rig of two cameras (Kinect v1/v2, Azure Kinect raw captures, 7-Scenes, ScanNet):
depth from one, colour from another, each with its own intrinsics and image size, a few centimetres apart.
A :class:`TwoCameraRig` describes them; :func:`register_depth` moves a depth image into the colour camera:
each depth pixel is back-projected with the depth intrinsics, moved by ``T_color_depth`` (identity when the
cameras are treated as co-located) and projected into the colour camera, where the nearest depth wins
(a z-buffer). Colour pixels that no depth pixel lands on (the colour camera's wider field of view, surfaces
the depth camera did not see) are 0, no measurement: nothing is interpolated. When a colour pixel is smaller
than a depth pixel (a colour camera of higher resolution, as ScanNet's), each depth pixel covers a square of
``ceil(f_color / f_depth)`` colour pixels, so the sampling ratio alone leaves no holes; at 7-Scenes' ratio
(525 / 585) every depth pixel lands on one colour pixel.

After registration the frame has one camera, the colour one: :class:`RGBDSequence` does this once per
``seq[i]``, so everything downstream (mapper, pose sources, held-out evaluation) sees colour-camera frames.

Sidecar format (``intrinsics.json`` of the plain-folder and TUM-style layouts): the top-level ``fx, fy, cx,
cy, width, height`` are the depth camera's; an optional ``color`` block describes the colour camera::

    "color": {"fx": 525.0, "fy": 525.0, "cx": 320.0, "cy": 240.0,   required
              "width": 640, "height": 480,                          optional, default: the depth image's size
              "T_color_depth": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],  optional 4x4 (or 16 numbers), metres:
                                                                    depth-camera points -> colour-camera points
              "poses_of": "depth",                                  optional: which camera the poses describe
              "note": "..."}                                        free text, ignored

``eligsir calibrate-color PATH --write`` estimates and writes this block (see :mod:`.color_calibration`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from ..io.atomic import atomic_write_text
from ..core.camera import Camera, check_pose, invert_pose

POSES_OF = ("depth", "color")


@dataclass(eq=False)
class TwoCameraRig:
    """A depth camera and a colour camera.

    depth, color: the intrinsics and image size of each. T_color_depth: [4, 4] rigid transform (metres) taking
    points from the depth camera's frame to the colour camera's (identity = co-located). poses_of: which camera
    the sequence's poses describe; with ``"depth"`` a frame's registered (colour-camera) pose is
    ``T_world_depth @ inv(T_color_depth)``.
    """

    depth: Camera
    color: Camera
    T_color_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    poses_of: str = "depth"

    def __post_init__(self) -> None:
        self.T_color_depth = check_pose(np.eye(4) if self.T_color_depth is None else self.T_color_depth,
                                        "T_color_depth")
        if self.poses_of not in POSES_OF:
            raise ValueError(f"poses_of must be one of {', '.join(POSES_OF)}, got {self.poses_of!r}")

    @property
    def is_identity(self) -> bool:
        """True when both cameras are the same and co-located: registration would change nothing."""
        return self.depth == self.color and bool(np.array_equal(self.T_color_depth, np.eye(4)))

    def color_pose(self, T_world_depth: np.ndarray) -> np.ndarray:
        """Camera-to-world pose of the colour camera from the depth camera's."""
        return np.asarray(T_world_depth, dtype=np.float64) @ invert_pose(self.T_color_depth)

    def register(self, depth: np.ndarray, depth_scale: float = 1.0) -> np.ndarray:
        """``depth`` [h, w] of the depth camera -> [H, W] of the colour camera (see :func:`register_depth`)."""
        return register_depth(depth, self.depth, self.color, self.T_color_depth, depth_scale=depth_scale)

    def __repr__(self) -> str:
        d, c = self.depth, self.color
        moved = "" if np.array_equal(self.T_color_depth, np.eye(4)) else \
            f", |t|={np.linalg.norm(self.T_color_depth[:3, 3]) * 100:.1f} cm"
        return (f"TwoCameraRig(depth {d.width}x{d.height} f={d.fx:g}, colour {c.width}x{c.height} f={c.fx:g}"
                f"{moved}, poses of the {self.poses_of} camera)")


def footprint(depth_cam: Camera, color_cam: Camera) -> int:
    """Side, in colour pixels, of the square each depth pixel covers: ceil of the focal-length ratio, at least 1."""
    ratio = max(color_cam.fx / depth_cam.fx, color_cam.fy / depth_cam.fy)
    return max(1, math.ceil(ratio - 1e-6))


def register_depth(depth: np.ndarray, depth_cam: Camera, color_cam: Camera, T_color_depth: np.ndarray | None = None,
                   *, depth_scale: float = 1.0) -> np.ndarray:
    """Reproject a depth image of ``depth_cam`` into ``color_cam`` with a z-buffer (nearest depth wins).

    depth: [h, w] (or [h, w, 1]) uint16 raw units or float metres-like units, 0 = no measurement, with
    ``value / depth_scale`` = metres (the scale only matters for the translation of ``T_color_depth``, metres).
    Returns [H, W] of the colour camera in the same units and dtype (integer depth is rounded to the nearest
    unit); colour pixels no depth pixel reaches are 0. Uses Open3D's PointCloud.project_to_depth_image.
    """
    depth = np.asarray(depth)
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.shape != (depth_cam.height, depth_cam.width):
        raise ValueError(f"depth image is {depth.shape[1] if depth.ndim == 2 else '?'}x{depth.shape[0]} but the "
                         f"depth camera is {depth_cam.width}x{depth_cam.height}")
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be positive, got {depth_scale}")
    T = np.eye(4) if T_color_depth is None else check_pose(T_color_depth, "T_color_depth").copy()
    T[:3, 3] *= depth_scale  # points stay in raw depth units throughout
    z = np.ascontiguousarray(depth, dtype=np.float32)
    image = o3d.t.geometry.Image(o3d.core.Tensor(z[..., None]))
    big = float(np.float32(3.0e38))  # no depth_max: the caller's depth_max applies later, in metres
    points = o3d.t.geometry.PointCloud.create_from_depth_image(
        image, o3d.core.Tensor(depth_cam.K), depth_scale=1.0, depth_max=big)
    out = None
    k = footprint(depth_cam, color_cam)
    for du in range(k):  # each depth pixel covers k x k colour pixels (k = 1 unless colour is finer than depth)
        for dv in range(k):
            off = (du - (k - 1) / 2.0, dv - (k - 1) / 2.0)
            K = color_cam.K.copy()
            K[0, 2] += off[0]
            K[1, 2] += off[1]
            img = points.project_to_depth_image(color_cam.width, color_cam.height, o3d.core.Tensor(K),
                                                o3d.core.Tensor(T), depth_scale=1.0, depth_max=big)
            z_new = img.as_tensor().numpy()[..., 0]
            if out is None:
                out = z_new.copy()
            else:
                closer = (z_new > 0) & ((out == 0) | (z_new < out))
                out[closer] = z_new[closer]
    if np.issubdtype(depth.dtype, np.integer):
        info = np.iinfo(depth.dtype)
        return np.clip(np.rint(out), 0, info.max).astype(depth.dtype)
    return out.astype(depth.dtype if np.issubdtype(depth.dtype, np.floating) else np.float32)


# -- the sidecar's colour block ------------------------------------------------------------------------------
def read_color_block(path: Path, depth_camera: Camera) -> TwoCameraRig | None:
    """The ``color`` block of an ``intrinsics.json`` sidecar as a rig with ``depth_camera``; None without one.

    Raises ValueError naming the file and field for a malformed block.
    """
    from ..io.inputs import read_json

    path = Path(path)
    data = read_json(path, "intrinsics")  # a regular file, size-capped
    block = data.get("color") if isinstance(data, dict) else None
    if block is None:
        return None
    where = f"{path}: \"color\" block"
    if not isinstance(block, dict):
        raise ValueError(f"{where} must be an object with fx, fy, cx, cy (got {type(block).__name__})")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in block]
    if missing:
        raise ValueError(f"{where}: missing field(s) {', '.join(missing)} (expected fx, fy, cx, cy and optionally "
                         f"width, height, T_color_depth, poses_of)")
    try:
        color = Camera(int(block.get("width", depth_camera.width)), int(block.get("height", depth_camera.height)),
                       float(block["fx"]), float(block["fy"]), float(block["cx"]), float(block["cy"]))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: bad intrinsics: {e}") from None
    T = np.eye(4)
    if block.get("T_color_depth") is not None:
        try:
            T = np.asarray(block["T_color_depth"], dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: T_color_depth must be a 4x4 matrix (4 rows of 4 numbers or 16 numbers)") \
                from None
    try:
        return TwoCameraRig(depth_camera, color, T, str(block.get("poses_of", "depth")))
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None


def write_color_block(path: Path, color: Camera, note: str = "", T_color_depth: np.ndarray | None = None) -> dict:
    """Add (or replace) the ``color`` block of the sidecar at ``path``, keeping every other key; returns it."""
    path = Path(path)
    data = json.loads(path.read_text()) if path.is_file() else {}
    old = data.get("color") if isinstance(data.get("color"), dict) else {}
    block = {"fx": round(color.fx, 3), "fy": round(color.fy, 3), "cx": round(color.cx, 3), "cy": round(color.cy, 3),
             "width": color.width, "height": color.height}
    if T_color_depth is not None and not np.array_equal(T_color_depth, np.eye(4)):
        block["T_color_depth"] = np.asarray(T_color_depth, dtype=np.float64).tolist()
    if "poses_of" in old:
        block["poses_of"] = old["poses_of"]
    if note:
        block["note"] = note
    data["color"] = block
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
    return block
