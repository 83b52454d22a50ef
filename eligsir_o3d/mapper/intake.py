"""An integrated input as a validated :class:`~eligsir_o3d.core.frame.Frame`: wrapped from an Open3D RGBD image (or
taken as a Frame), at its pose, camera and timestamp, each checked with the frame's index in the error."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..core.camera import Camera, check_pose
from ..core.frame import Frame, FrameError


def checked_pose(pose, index: int) -> np.ndarray:
    """``pose`` as a 4x4 rigid T_world_cam, or :class:`FrameError` naming frame ``index``."""
    try:
        return check_pose(pose, f"frame {index}: pose")
    except ValueError as e:
        raise FrameError(str(e)) from None


def to_frame(rgbd, pose, timestamp: float | None, *, index: int, camera: Camera, config,
             last_timestamp: float | None, track: Callable[[Frame], np.ndarray]) -> Frame:
    """The Frame of input number ``index``: ``rgbd`` (a legacy or tensor RGBDImage, or a Frame) at ``pose``
    (None: ``track(frame)`` gives it). ``timestamp`` defaults to ``index`` frame periods. Raises FrameError when
    the camera differs from ``camera`` or the timestamp is not after ``last_timestamp``."""
    ts = float(timestamp) if timestamp is not None else index * config.clock.frame_period_s
    if isinstance(rgbd, Frame):
        frame = rgbd
        if pose is not None:
            frame.T_world_cam = checked_pose(pose, frame.index)
    else:
        given = np.eye(4) if pose is None else pose  # no pose: decoded at the identity, then tracked
        frame = Frame.from_rgbd(rgbd, camera, given, depth_scale=config.depth_scale, depth_max=config.depth_max,
                                timestamp=ts, index=index)
        if pose is None:
            frame.T_world_cam = track(frame)
    if frame.camera != camera:
        raise FrameError(f"frame {frame.index}: camera {frame.camera} differs from the reconstructor's {camera}")
    if last_timestamp is not None and not frame.timestamp > last_timestamp:
        raise FrameError(f"frame {frame.index}: timestamp {frame.timestamp:g} s is not after the previous "
                         f"frame's {last_timestamp:g} s (timestamps must increase)")
    return frame
