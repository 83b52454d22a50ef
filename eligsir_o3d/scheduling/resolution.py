"""Scales that follow the camera's resolution, on cameras larger than 640x480.

The support render's scale, the fidelity controller's idle floor and the budget cap's pricing scale are set for a
640x480 stream, where 1/4 is a 160x120 image. On a larger camera the same fraction is more work: at 1280x960 every
update at the 1/4 floor supervises 320x240 pixels, four times a 640x480 stream's, and each frame's support render
is four times as large (lab: fidelity-idle-floor). So on a larger camera each of them is the configured scale
times :func:`camera_factor`, a power of two (whole-pixel area averages of the source): 1/2 for 1280x960 or 1280x720,
1/4 for 2560x1920; 640x480 and 848x480 streams keep the configured scales, and so do smaller cameras (a finer
support render for a smaller stream seeds it more densely, which helps at one budget and hurts at another, lab:
resolution-small-cameras).
"""

from __future__ import annotations

import math

from ..core.camera import Camera

REFERENCE_PIXELS = 640 * 480  # the stream the configured scales are meant for


def camera_factor(camera: Camera, pixels: int = REFERENCE_PIXELS) -> float:
    """The power of two nearest sqrt(pixels / camera's pixels): a scale set for a stream of ``pixels`` pixels,
    times this, gives an image of ``camera`` of about the same size."""
    return 2.0 ** round(0.5 * math.log2(pixels / max(1, camera.pixels)))


def coarser_for(scale: float, camera: Camera | None, follow: bool = True) -> float:
    """``scale`` (set for a 640x480 stream) for ``camera``: coarser on a larger image, as set on a smaller one;
    ``scale`` itself without a camera or with ``follow`` off (each scale's ``*_follow*_camera`` switch)."""
    if camera is None or not follow:
        return float(scale)
    return scale * min(1.0, camera_factor(camera))
