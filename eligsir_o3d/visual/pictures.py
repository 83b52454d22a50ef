"""Held-out comparison pictures: what a person looks at to judge a map.

One PNG per chosen held-out view, ``heldout/<frame index, 6 digits>.png``, a 3 x 2 grid (panels at most
480 pixels wide; a palette PNG of at most 300 kB, so that six of them do not outweigh the map):

    reference image   | render                 | |colour error| (inferno, 0 .. 0.25)
    sensor depth      | rendered depth         | |depth error| (inferno, 0 .. 0.25 m)

Depth panels share one turbo scale (0 .. the 98th percentile of the sensor's depth), black where there is no
measurement (sensor) or nothing was rendered (alpha < 0.5). The title bar names the frame and its PSNR and depth
RMSE, computed exactly as ``metrics.json`` computes them (:mod:`eligsir_o3d.eval.metrics`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

COLOR_ERROR_MAX = 0.25  # mean absolute RGB error shown at full scale
DEPTH_ERROR_MAX_M = 0.25
TITLE_PX = 34
PANEL_WIDTH = 480  # 640x480 views become 480x360 panels
MAX_PICTURE_BYTES = 300_000  # a held-out picture is a palette PNG of at most this (full colour: ~1.4 MB)


def spread(n: int, count: int) -> list[int]:
    """``count`` positions spread evenly over ``range(n)``, first and last included."""
    if n <= 0 or count <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(count, n))})


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _colormap(values: np.ndarray, vmax: float, cmap: int, invalid: np.ndarray | None = None) -> np.ndarray:
    """[H, W] values in 0 .. vmax -> [H, W, 3] uint8 RGB through an OpenCV colour map; ``invalid`` pixels black."""
    import cv2

    scaled = _u8(np.nan_to_num(values, nan=0.0) / max(vmax, 1e-9))
    rgb = cv2.applyColorMap(scaled, cmap)[..., ::-1].copy()
    if invalid is not None:
        rgb[invalid] = 0
    return rgb


def _label(panel: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` on a dark band at the top-left of ``panel`` (scaled to the panel's width)."""
    import cv2

    s = max(panel.shape[1] / 560.0, 0.5)
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * s, max(1, round(1.5 * s)))
    out = panel.copy()
    out[: h + base + int(10 * s), : w + int(12 * s)] //= 3
    cv2.putText(out, text, (int(6 * s), h + int(5 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * s, (255, 255, 255),
                max(1, round(1.5 * s)), cv2.LINE_AA)
    return out


def comparison_picture(ref_color, ref_depth, color, depth, alpha, title: str,
                       max_panel_width: int | None = PANEL_WIDTH) -> np.ndarray:
    """The 3 x 2 comparison grid as [2h + title, 3w, 3] uint8 RGB, panels h x w (the image size, shrunk to
    ``max_panel_width`` wide if larger; scores are computed at full size). Inputs are [H, W(, 3)] arrays or
    tensors: reference colour and sensor depth (metres, 0 = none), rendered colour, depth and alpha."""
    import cv2

    from ..eval.metrics import depth_errors, psnr

    def np_(x):
        return x.detach().float().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float32)

    ref_color, ref_depth, color, depth, alpha = map(np_, (ref_color, ref_depth, color, depth, alpha))
    p = psnr(torch.from_numpy(np.clip(color, 0, 1)), torch.from_numpy(ref_color))
    sse, n = depth_errors(torch.from_numpy(depth), torch.from_numpy(ref_depth))
    rmse = math.sqrt(sse / n) if n else float("nan")
    no_sensor = ~(np.isfinite(ref_depth) & (ref_depth > 0))
    no_render = alpha < 0.5
    valid_depth = ref_depth[~no_sensor]
    dmax = float(np.percentile(valid_depth, 98)) if valid_depth.size else max(float(np.nanmax(depth)), 1.0)
    err = np.abs(np.clip(color, 0, 1) - ref_color).mean(-1)
    derr = np.abs(depth - ref_depth)
    h, w = ref_color.shape[:2]
    size = (w, h) if max_panel_width is None or w <= max_panel_width else \
        (max_panel_width, max(1, round(h * max_panel_width / w)))

    def fit(img):
        return img if size == (w, h) else cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    panels = [
        _label(fit(_u8(ref_color)), "reference"),
        _label(fit(_u8(color)), f"render  PSNR {p:.2f} dB"),
        _label(fit(_colormap(err, COLOR_ERROR_MAX, cv2.COLORMAP_INFERNO)), f"|colour error|  0-{COLOR_ERROR_MAX:g}"),
        _label(fit(_colormap(ref_depth, dmax, cv2.COLORMAP_TURBO, no_sensor)), f"sensor depth  0-{dmax:.1f} m"),
        _label(fit(_colormap(depth, dmax, cv2.COLORMAP_TURBO, no_render)), "rendered depth"),
        _label(fit(_colormap(derr, DEPTH_ERROR_MAX_M, cv2.COLORMAP_INFERNO, no_sensor | no_render)),
               f"|depth error|  0-{DEPTH_ERROR_MAX_M:g} m  RMSE {rmse:.3f} m"),
    ]
    grid = np.concatenate([np.concatenate(panels[:3], 1), np.concatenate(panels[3:], 1)], 0)
    bar = np.full((TITLE_PX, grid.shape[1], 3), 24, np.uint8)
    cv2.putText(bar, f"{title}   PSNR {p:.2f} dB   depth RMSE {rmse:.3f} m", (8, TITLE_PX - 10),
                cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    return np.concatenate([bar, grid], 0)


def small_png(rgb: np.ndarray, max_bytes: int = MAX_PICTURE_BYTES) -> bytes:
    """``rgb`` [H, W, 3] uint8 as a palette PNG of at most ``max_bytes``: 256 colours (octree, no dithering: the
    colour maps and text stay crisp), then 128, then the picture scaled down by 0.8 steps (down to 1/2 at most,
    which stays legible). A full-colour PNG of a 1440 x 754 comparison grid is ~1.5 MB; this ~0.3 MB."""
    import io

    import cv2
    from PIL import Image

    img = np.ascontiguousarray(rgb)
    data = b""
    for step in range(4):
        for colors in (256, 128):
            buf = io.BytesIO()
            Image.fromarray(img).quantize(colors, method=Image.Quantize.FASTOCTREE,
                                          dither=Image.Dither.NONE).save(buf, "PNG", optimize=True)
            data = buf.getvalue()
            if len(data) <= max_bytes:
                return data
        size = (max(1, round(rgb.shape[1] * 0.8 ** (step + 1))), max(1, round(rgb.shape[0] * 0.8 ** (step + 1))))
        img = cv2.resize(np.ascontiguousarray(rgb), size, interpolation=cv2.INTER_AREA)
    return data


def write_png(path: Path, rgb: np.ndarray, max_bytes: int | None = None) -> Path:
    """``rgb`` [H, W, 3] uint8 as a PNG, atomically; with ``max_bytes``, a palette PNG of at most that size
    (:func:`small_png`)."""
    import cv2

    from ..io.atomic import atomic_write

    if max_bytes is not None:
        data = small_png(rgb, max_bytes)
        return atomic_write(path, lambda f: f.write(data))
    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    return atomic_write(path, lambda f: f.write(png.tobytes()))  # a full disk leaves the old picture intact


@torch.no_grad()
def write_heldout_pictures(out_dir: str | Path, frames: Sequence, render_fn: Callable, count: int = 6) -> list[Path]:
    """``out_dir/NNNNNN.png`` for ``count`` held-out ``frames`` (:class:`eligsir_o3d.core.frame.Frame`) spread over
    the sequence; ``render_fn(frame)`` -> RenderOutput at the frame's pose and camera. Returns the paths."""
    paths = []
    for k in spread(len(frames), count):
        f = frames[k]
        out = render_fn(f)
        pic = comparison_picture(f.color, f.depth, out.color, out.depth, out.alpha,
                                 f"held-out frame {f.index}  t={f.timestamp:.2f} s")
        paths.append(write_png(Path(out_dir) / f"{f.index:06d}.png", pic, max_bytes=MAX_PICTURE_BYTES))
    return paths
