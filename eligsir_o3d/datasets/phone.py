"""What iPhone / iPad LiDAR captures have in common (Record3D, Stray Scanner, Polycam), in one place.

- Camera axes: ARKit's camera looks down -z with y up (OpenGL). Our poses are OpenCV's (x right, y down, z
  forward): ``T_cv = T_gl @ diag(1, -1, -1, 1)`` (:func:`gl_to_cv`). Stray Scanner applies that flip itself.
- Two cameras, one pose: the LiDAR depth is low resolution (256 x 192 on current devices) with its own
  intrinsics (the colour camera's, scaled to the depth size), aligned to the colour camera by ARKit (same pose,
  ``T_color_depth`` = identity). Depth is registered into the colour camera by the existing two-camera path
  (:mod:`.registration`): each depth pixel covers a square of colour pixels, nothing is interpolated.
- Colour much larger than depth (1920 x 1440 against 256 x 192) is scaled down to ``color_width`` pixels wide
  (default 640): the mapper supervises at a fraction of that anyway, and registration stays cheap.
- Confidence (ARKit's 0 low, 1 medium, 2 high) drops depth below ``min_confidence`` (default 1: keep medium and
  high). Depth beyond ``max_depth`` metres (default 5.0) is dropped as unreliable (the LiDAR's range).
- Depth is float32 metres (``depth_scale`` 1.0) after reading, 0 = no measurement.
- Frames without a pose (or with a lost-tracking marker) are left out at open time and listed in
  ``skipped_frames``, as for other readers' bad frames.

Reader options, for every phone format: ``min_confidence`` (0, 1, 2), ``max_depth`` (m), ``color_width`` (px),
``fps`` (where the capture has no clock).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import open3d as o3d

from ..core.camera import Camera
from .base import DatasetError, RGBDSequence

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: OpenGL (x right, y up, z back) -> OpenCV


def gl_to_cv(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with OpenGL camera axes [4, 4] -> the same camera with OpenCV axes (its own inverse)."""
    return np.asarray(T_world_cam_gl, dtype=np.float64) @ GL_TO_CV


@dataclass
class PhoneOptions:
    """Reader options every phone format shares (see the module docstring)."""

    min_confidence: int = 1
    max_depth: float = 5.0
    color_width: int = 640

    def __post_init__(self) -> None:
        if self.min_confidence not in (0, 1, 2):
            raise DatasetError(f"min_confidence must be 0 (keep all), 1 (medium and high) or 2 (high only), got "
                               f"{self.min_confidence}")
        if not self.max_depth > 0:
            raise DatasetError(f"max_depth must be positive (metres), got {self.max_depth}")
        if int(self.color_width) < 16:
            raise DatasetError(f"color_width must be at least 16 pixels, got {self.color_width}")


def scaled_to(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` (intrinsics of one image size) for an image of ``width`` x ``height`` covering the same view."""
    if (width, height) == (camera.width, camera.height):
        return camera
    sx, sy = width / camera.width, height / camera.height
    return Camera(int(width), int(height), camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5,
                  (camera.cy + 0.5) * sy - 0.5)


def frame_camera(color: Camera, color_width: int) -> Camera:
    """The colour camera of the frames: ``color`` scaled down to ``color_width`` pixels wide when wider."""
    if color.width <= color_width:
        return color
    return scaled_to(color, int(color_width), max(1, int(round(color.height * color_width / color.width))))


def clean_depth(depth_m: np.ndarray, confidence: np.ndarray | None, opts: PhoneOptions) -> np.ndarray:
    """Depth [h, w] float metres with non-finite values, depth beyond ``max_depth`` and pixels of confidence below
    ``min_confidence`` set to 0 (no measurement). Returns float32 [h, w]."""
    d = np.array(depth_m, dtype=np.float32)
    bad = ~np.isfinite(d) | (d < 0) | (d > opts.max_depth)
    if confidence is not None and opts.min_confidence > 0:
        bad |= confidence < opts.min_confidence
    d[bad] = 0.0
    return d


def confidence_levels(conf: np.ndarray) -> np.ndarray:
    """Confidence as ARKit's levels 0/1/2 (uint8): values already in 0..2 stay, 8-bit images (0/127/255 or
    similar) are mapped by thirds."""
    conf = np.asarray(conf)
    if conf.size and conf.max() > 2:
        return np.clip(np.rint(conf.astype(np.float32) / 127.5), 0, 2).astype(np.uint8)
    return conf.astype(np.uint8)


def read_confidence_png(path: Path, i: int) -> np.ndarray | None:
    """Confidence levels 0/1/2 (uint8 [h, w]) from an 8-bit PNG (the first channel of a colour one), or None when
    the file is absent (confidence is optional in every phone layout)."""
    if not path.is_file():
        return None
    import cv2

    c = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if c is None:
        raise DatasetError(f"frame {i}: confidence file {path} is corrupt")
    return confidence_levels(c if c.ndim == 2 else c[..., 0])


Native = Callable[[int], tuple[np.ndarray, np.ndarray, "np.ndarray | None"]]


class PhoneSequence(RGBDSequence):
    """A phone capture: ``native(i)`` gives frame i as recorded -- colour uint8 [Hc, Wc, 3] RGB, depth float32
    metres [h, w], confidence uint8 [h, w] (0/1/2) or None -- and the sequence scales colour down, cleans depth
    and (through :class:`RGBDSequence`) registers depth into the colour camera.

    color_native: intrinsics of the recorded colour images; depth_native: of the depth images (same pose).
    """

    def __init__(self, *, native: Native, color_native: Camera, depth_native: Camera, opts: PhoneOptions,
                 where: Callable[[int], str], **kwargs) -> None:
        color = frame_camera(color_native, opts.color_width)
        rig = {} if color == depth_native else {"color_camera": color, "poses_of": "color"}
        super().__init__(camera=depth_native, depth_scale=1.0, **rig, **kwargs)
        self._native, self._where, self.opts = native, where, opts
        self.color_intrinsic, self.depth_intrinsic = color_native, depth_native
        self.T_color_depth = np.eye(4)

    def read_native(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Frame i as recorded (see the class docstring), sizes checked against the capture's intrinsics."""
        i = self._index(int(i))
        color, depth, conf = self._native(i)
        c, d = self.color_intrinsic, self.depth_intrinsic
        if color.ndim != 3 or color.shape[:2] != (c.height, c.width):
            raise DatasetError(f"frame {i}: colour {self._where(i)} is {color.shape[1]}x{color.shape[0]} but the "
                               f"capture's intrinsics are for {c.width}x{c.height}")
        if depth.shape != (d.height, d.width):
            raise DatasetError(f"frame {i}: depth {self._where(i)} is {depth.shape[1]}x{depth.shape[0]}, expected "
                               f"{d.width}x{d.height}")
        if conf is not None and conf.shape != depth.shape:
            raise DatasetError(f"frame {i}: confidence of {self._where(i)} is {conf.shape[1]}x{conf.shape[0]}, "
                               f"expected {d.width}x{d.height} like the depth")
        return color, depth, conf

    def _read_images(self, i: int) -> tuple[o3d.t.geometry.Image, o3d.t.geometry.Image]:
        color, depth, conf = self.read_native(i)
        cam = self.camera
        if color.shape[:2] != (cam.height, cam.width):
            import cv2

            color = cv2.resize(color, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        depth = clean_depth(depth, conf, self.opts)
        return (o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color[..., :3]))),
                o3d.t.geometry.Image(o3d.core.Tensor(depth[..., None])))


def check_frame_count(path: Path, what: str, have: int, need: int) -> None:
    """One-line error naming ``path`` when it describes fewer frames than the capture has."""
    if have < need:
        raise DatasetError(f"{path}: {what} for {have} frames but the capture has {need} (truncated file?)")


PROBED_FILES = 5  # readable depth files whose most common size is the capture's depth size


def probe_size(frames: list, size_of: Callable[[object], tuple[int, int]], where: str) -> tuple[int, int]:
    """The depth size (w, h) of a capture that does not declare it: the most common ``size_of(frame)`` among the
    first :data:`PROBED_FILES` frames that can be read. An unreadable or odd-sized file is its own frame's fault
    (the bad-frame rule applies when the stream reaches it), not the capture's."""
    return probe_sizes(frames, size_of, where)[0]


def probe_sizes(frames: list, size_of: Callable[[object], tuple[int, int]], where: str):
    """(size, the first frame of that size) of :func:`probe_size`."""
    sizes, seen, first_error = [], [], None
    for n in frames[:4 * PROBED_FILES]:
        try:
            sizes.append(tuple(size_of(n)))
            seen.append(n)
        except (ValueError, OSError) as e:
            first_error = first_error or e
        if len(sizes) == PROBED_FILES:
            break
    if not sizes:
        raise DatasetError(f"{where}: none of the first {min(len(frames), 4 * PROBED_FILES)} depth files can be "
                           f"read ({first_error})")
    best = max(set(sizes), key=lambda s: (sizes.count(s), -sizes.index(s)))
    return best, seen[sizes.index(best)]


def import_lzfse():
    """The ``liblzfse`` module (PyPI ``pyliblzfse``), with an install hint when it is missing."""
    try:
        import liblzfse
    except ImportError:
        raise DatasetError("reading Record3D .r3d depth needs LZFSE: pip install pyliblzfse "
                           "(or pip install 'eligsir-o3d[phone]')") from None
    return liblzfse
