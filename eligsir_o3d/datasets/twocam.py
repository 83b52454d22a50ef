"""Two cameras: recordings whose depth comes from a different camera than the colour (ScanNet, ROS bags).

Such a reader exposes both cameras on the sequence -- ``color_intrinsic``, ``depth_intrinsic`` (:class:`Camera`),
``T_color_depth`` (4x4 depth-camera-to-colour-camera, or None when the recording does not say) and ``registered``
(True when depth is already aligned to colour, e.g. a RealSense ``aligned_depth_to_color`` topic) -- and hands
every frame's native images to :func:`combine`. Depth that is not yet aligned is then registered into the colour
camera by :class:`~.base.RGBDSequence` (see :mod:`.registration`), once per frame as it is read, so the frames'
camera (``seq.camera``) is the colour one; :meth:`TwoCameras.sequence_kwargs` says so to the sequence.
A colour camera finer than the depth one (ScanNet: 1296x968 colour, 640x480 depth) is scaled down to the depth
image's width first: the mapper would supervise at a fraction of that resolution anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera


@dataclass
class TwoCameras:
    color_intrinsic: Camera
    depth_intrinsic: Camera
    T_color_depth: np.ndarray | None = None
    registered: bool = False

    @property
    def color_camera(self) -> Camera:
        """The colour camera of the frames: the recorded one, scaled down to the depth image's width when finer."""
        c, d = self.color_intrinsic, self.depth_intrinsic
        return c if self.registered or c.width <= d.width else c.scaled(d.width / c.width)

    def sequence_kwargs(self, poses_of: str = "depth") -> dict:
        """Keyword arguments for :class:`~.base.RGBDSequence`: the depth camera as read, and, unless depth is
        already aligned, the colour camera that depth is registered into at read time."""
        if self.registered:
            return {"camera": self.color_camera}
        return {"camera": self.depth_intrinsic, "color_camera": self.color_camera,
                "T_color_depth": self.T_color_depth, "poses_of": poses_of}


def combine(color: np.ndarray, depth: np.ndarray, cams: TwoCameras) -> tuple[np.ndarray, np.ndarray]:
    """Native colour [Hc, Wc, 3] uint8 and depth [Hd, Wd] -> colour on ``cams.color_camera``'s grid and depth on
    the depth camera's (registered later by the sequence), or on the colour grid when already aligned."""
    cam = cams.color_camera
    if color.shape[:2] != (cam.height, cam.width):
        import cv2

        color = cv2.resize(color, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    if cams.registered and depth.shape[:2] != (cam.height, cam.width):
        import cv2

        depth = cv2.resize(depth, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(color), np.ascontiguousarray(depth)
