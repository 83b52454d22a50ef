"""Where a render's error lies: in the reference's detail or in its broad colour, and how far the render sits off.

A held-out PSNR mixes three things that call for different remedies: a map that lacks resolution (its error sits on
the reference's edges and texture), a map whose colour is off (its error survives a blur of both images), and a
view whose pose disagrees with its image (the render matches better once shifted by a few pixels). For one render
and its reference, on the pixels of a mask:

- :func:`detail_split`: PSNR on the reference's *detail* pixels (the ``detail_share`` of masked pixels with the
  largest Sobel gradient of the reference's luminance; 0.2: its edges and texture) and on the others (*flat*), and
  the PSNR of both images blurred alike (a Gaussian of ``lowpass_sigma`` pixels: broad colour only);
- :func:`best_shift`: the whole-pixel shift of the render, within ``radius`` pixels, that minimises its MSE against
  the reference on the masked pixels, and the PSNR there: how much of the error a small pose error explains.

Images are [H, W, 3] float arrays in [0, 1] (numpy or torch on the CPU); OpenCV does the filtering.
"""

from __future__ import annotations

import numpy as np

from .metrics import mse_to_psnr, psnr

DETAIL_SHARE = 0.2  # share of the masked pixels, by the reference's gradient, that counts as its detail
LOWPASS_SIGMA = 6.0  # pixels: the blur that keeps broad colour only (a 640x480 view's ~50 px features)
SHIFT_RADIUS = 12  # pixels searched by best_shift in each direction


def _rgb(x, name: str) -> np.ndarray:
    a = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{name} must be an [H, W, 3] image, got shape {list(a.shape)}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _mask(mask, shape) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    m = np.asarray(mask.cpu() if hasattr(mask, "cpu") else mask).astype(bool)
    if m.shape != shape:
        raise ValueError(f"mask must be [H, W] = {list(shape)}, got {list(m.shape)}")
    return m


def detail_split(pred, ref, mask=None, detail_share: float = DETAIL_SHARE,
                 lowpass_sigma: float = LOWPASS_SIGMA) -> dict:
    """{"detail": dB, "flat": dB, "lowpass": dB, "detail_pixels": n}: see the module docstring."""
    import cv2

    p, r = _rgb(pred, "pred"), _rgb(ref, "ref")
    if p.shape != r.shape:
        raise ValueError(f"pred {list(p.shape)} and ref {list(r.shape)} differ in shape")
    if not 0.0 < detail_share < 1.0:
        raise ValueError(f"detail_share must lie in (0, 1), got {detail_share}")
    m = _mask(mask, r.shape[:2])
    gray = cv2.cvtColor(r, cv2.COLOR_RGB2GRAY)
    grad = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
    if not m.any():
        return {"detail": float("nan"), "flat": float("nan"), "lowpass": float("nan"), "detail_pixels": 0}
    # rank, not a threshold: ties (a flat reference) still split into the requested shares
    order = np.argsort(grad[m], kind="stable")
    detail = np.zeros(int(m.sum()), bool)
    detail[order[len(order) - max(1, int(round(detail_share * len(order)))):]] = True
    is_detail = np.zeros_like(m)
    is_detail[m] = detail
    p_low, r_low = (cv2.GaussianBlur(x, (0, 0), lowpass_sigma) for x in (p, r))
    return {"detail": psnr(p, r, is_detail), "flat": psnr(p, r, m & ~is_detail), "lowpass": psnr(p_low, r_low, m),
            "detail_pixels": int(is_detail.sum())}


def best_shift(pred, ref, mask=None, radius: int = SHIFT_RADIUS, valid=None) -> dict:
    """{"dx": px, "dy": px, "psnr": dB at that shift, "psnr_unshifted": dB}: the render moved by (dx, dy) whole
    pixels (right and down positive) matches the reference best. ``mask`` [H, W] (reference pixels that count)
    stays in place; ``valid`` [H, W] (the render's pixels that have content, e.g. where a TSDF's ray hit a surface)
    moves with the render, so that a shift is neither charged for the holes it moves into the mask nor credited
    for moving them out. Only pixels at least ``radius`` from the border count, for every shift alike."""
    import cv2

    p, r = _rgb(pred, "pred"), _rgb(ref, "ref")
    if p.shape != r.shape:
        raise ValueError(f"pred {list(p.shape)} and ref {list(r.shape)} differ in shape")
    h, w = r.shape[:2]
    if radius < 0 or 2 * radius >= min(h, w):
        raise ValueError(f"radius must be >= 0 and leave pixels inside the {w}x{h} image, got {radius}")
    inner = (slice(radius, h - radius), slice(radius, w - radius))
    m = _mask(mask, (h, w))[inner].astype(np.float32)
    v = _mask(valid, (h, w)).astype(np.float32)
    # every shift at once, as correlations of the render's window with the reference's inner part (OpenCV's
    # template matching): sum over counted pixels of v p^2 - 2 v p r + v r^2, and the count; the whole grid, since
    # a coarse-to-fine search locks onto the wrong period of a regular texture (stripes, tiles)
    r_in = r[inner]

    def corr(image: np.ndarray, templ: np.ndarray) -> np.ndarray:
        return cv2.matchTemplate(np.ascontiguousarray(image, np.float32), np.ascontiguousarray(templ, np.float32),
                                 cv2.TM_CCORR).astype(np.float64)

    vp = p * v[..., None]
    sse = corr(vp * p, np.repeat(m[..., None], 3, -1)) - 2.0 * corr(vp, r_in * m[..., None]) \
        + corr(np.repeat(v[..., None], 3, -1), r_in * r_in * m[..., None])
    count = 3.0 * corr(v, m)
    enough = count >= 0.5 * 3.0 * m.sum()  # a shift must keep at least half the counted pixels
    if not enough[radius, radius]:
        return {"dx": 0, "dy": 0, "psnr": float("nan"), "psnr_unshifted": float("nan")}
    mse = np.where(enough, np.maximum(sse, 0.0) / np.maximum(count, 1.0), np.inf)  # [2R+1, 2R+1], window (y, x)
    ys, xs = np.mgrid[0:2 * radius + 1, 0:2 * radius + 1]
    dys, dxs = radius - ys, radius - xs  # the window starting at (y, x) is the render moved by (R - x, R - y)
    # ties (within float32 rounding of a perfect match) go to the smaller shift
    key = np.lexsort(((np.abs(dxs) + np.abs(dys)).ravel(), np.round(mse.ravel(), 9)))
    k = key[0]
    return {"dx": int(dxs.ravel()[k]), "dy": int(dys.ravel()[k]), "psnr": mse_to_psnr(float(mse.ravel()[k])),
            "psnr_unshifted": mse_to_psnr(float(mse[radius, radius]))}
