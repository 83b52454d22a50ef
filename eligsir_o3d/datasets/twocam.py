"""Two cameras: recordings whose depth comes from a different camera than the colour (ScanNet, ROS bags).

Such a reader exposes both cameras on the sequence -- ``color_intrinsic``, ``depth_intrinsic`` (:class:`Camera`),
``T_color_depth`` (4x4 depth-camera-to-colour-camera, or None when the recording does not say) and ``registered``
(True when depth is already aligned to colour, e.g. a RealSense ``aligned_depth_to_color`` topic) -- and hands
every frame's native images to :func:`combine`, the one place that turns them into the same-size pair a frame
needs. Until depth is registered into the colour camera, ``combine`` keeps the depth camera as the frame's camera
(``seq.camera``) and resizes colour to the depth grid: that is a resize, not a registration (the colour pixels
stay where the colour camera saw them, a few pixels off the depth for a camera pair ~2.5 cm apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera


@dataclass
class TwoCameras:
    color_intrinsic: Camera
    depth_intrinsic: Camera
    T_color_depth: np.ndarray | None = None
    registered: bool = False

    @property
    def frame_camera(self) -> Camera:
        """The camera of the frames the sequence returns (see :func:`combine`)."""
        return self.color_intrinsic if self.registered else self.depth_intrinsic


def combine(color: np.ndarray, depth: np.ndarray, cams: TwoCameras) -> tuple[np.ndarray, np.ndarray]:
    """Native colour [Hc, Wc, 3] uint8 and depth [Hd, Wd] -> a pair on ``cams.frame_camera``'s grid."""
    cam = cams.frame_camera
    if color.shape[:2] != (cam.height, cam.width):
        import cv2

        color = cv2.resize(color, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    if depth.shape[:2] != (cam.height, cam.width):
        import cv2

        depth = cv2.resize(depth, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(color), np.ascontiguousarray(depth)
