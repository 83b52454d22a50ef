"""Scales that follow the camera's resolution.

The support render's scale, the fidelity controller's idle floor and the budget cap's pricing scale are set for a
640x480 stream, where 1/4 is a 160x120 image. The same fraction of another camera's image is another amount of
work and detail: at 320x240 the support render would be 80x60, so new space is seeded a quarter as densely (a
7-Scenes kitchen stretch resampled to 320x240: 21.81 dB against the TSDF's 21.02; with a 160x120 render 23.57), and
at 1280x960 every update at the 1/4 floor supervises 320x240 pixels, four times the work of a 640x480 stream's (the
same stretch resampled to 1280x960: 788 updates, 21.58 dB; floor, cap pricing and render at 160x120: 2020 updates,
22.60). So each of these scales is the configured one times :func:`camera_factor`, a power of two (whole-pixel area
averages of the source): 1 for 640x480 (and 848x480), 2 for 320x240, 1/2 for 1280x960 or 1280x720.
"""

from __future__ import annotations

import math

from ..core.camera import Camera

REFERENCE_PIXELS = 640 * 480  # the stream the configured scales are meant for


def camera_factor(camera: Camera, pixels: int = REFERENCE_PIXELS) -> float:
    """The power of two nearest sqrt(pixels / camera's pixels): a scale set for a stream of ``pixels`` pixels,
    times this, gives an image of ``camera`` of about the same size."""
    return 2.0 ** round(0.5 * math.log2(pixels / max(1, camera.pixels)))


def coarser_for(scale: float, camera: Camera) -> float:
    """``scale`` (set for a 640x480 stream) for ``camera``: coarser on a larger image, never finer (an idle floor,
    a price: finer would make a small camera's updates dearer than a 640x480 stream's)."""
    return scale * min(1.0, camera_factor(camera))


def following(scale: float, camera: Camera, finest: float) -> float:
    """``scale`` (set for a 640x480 stream) for ``camera``: coarser on a larger image, finer on a smaller one but not
    beyond ``finest`` (nor beyond ``scale`` itself where that is finer)."""
    return min(scale * camera_factor(camera), max(scale, finest))
