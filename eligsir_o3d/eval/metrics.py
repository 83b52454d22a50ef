"""Image and depth metrics on held-out views (paper, "Evaluation Protocol").

Conventions shared by every function here:
- Colour is RGB float in [0, 1], shape [H, W, 3] (torch or numpy). Predictions are clamped to [0, 1] before
  scoring (a rasteriser can overshoot slightly; the paper scores RGB normalised to [0, 1]).
- Missing renders count as failures (paper): a non-finite predicted colour value scores a squared error of 1.0
  (the largest possible on [0, 1]); a whole missing view (``render_fn`` returned None) scores MSE 1.0, i.e.
  PSNR 0 dB, SSIM 0.0, LPIPS 1.0 (when LPIPS is available) - see :data:`MISSING`.
- PSNR uses the same floor as the paper's cell PSNR: ``-10 log10(max(mse, EPS))`` with ``EPS = 1e-12``, so a
  perfect render scores ``PSNR_CAP = 120 dB`` rather than infinity.
"""

from __future__ import annotations

import importlib.util
import math
import os
from pathlib import Path

import numpy as np
import torch

EPS = 1e-12  # the paper's epsilon in q_c = -10 log10(max(e_c, eps)); used for image PSNR as well
PSNR_CAP = -10.0 * math.log10(EPS)  # 120 dB: what a perfect render scores
MISSING = {"psnr": 0.0, "ssim": 0.0, "lpips": 1.0}  # scores of a view whose render is missing (a failure)


def _as_tensor(x, name: str) -> torch.Tensor:
    if x is None:
        raise ValueError(f"{name} is None")
    t = x if isinstance(x, torch.Tensor) else torch.from_numpy(np.asarray(x))
    return t.detach().to("cpu", torch.float32)


def _rgb_pair(pred, ref) -> tuple[torch.Tensor, torch.Tensor]:
    """pred, ref -> float32 CPU [H, W, 3]; pred clamped to [0, 1], non-finite pred replaced by the worst value."""
    p, r = _as_tensor(pred, "pred"), _as_tensor(ref, "ref")
    if p.shape != r.shape or p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"colour images must both be [H, W, 3]; got pred {tuple(p.shape)} and ref {tuple(r.shape)}")
    worst = (r < 0.5).float()  # the value in {0, 1} farthest from the reference (for SSIM / LPIPS only)
    p = torch.where(torch.isfinite(p), p.clamp(0.0, 1.0), worst)
    return p, r


def squared_errors(pred, ref) -> torch.Tensor:
    """Per-pixel, per-channel squared RGB error [H, W, 3] (pred clamped to [0, 1]; non-finite pred -> 1.0)."""
    p, r = _as_tensor(pred, "pred"), _as_tensor(ref, "ref")
    if p.shape != r.shape or p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"colour images must both be [H, W, 3]; got pred {tuple(p.shape)} and ref {tuple(r.shape)}")
    se = (p.clamp(0.0, 1.0) - r).square_()
    bad = ~torch.isfinite(p)
    if bad.any():
        se[bad] = 1.0
    return se


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB of an RGB mean squared error on [0, 1] with the paper's floor (cap 120 dB)."""
    return float(-10.0 * math.log10(max(float(mse), EPS)))


def psnr(pred, ref, mask=None) -> float:
    """PSNR in dB of pred [H, W, 3] against ref [H, W, 3], both RGB in [0, 1].

    MSE is the mean over pixels (those where ``mask`` [H, W] is true, if given) and the three channels;
    PSNR = -10 log10(max(MSE, 1e-12)), i.e. capped at 120 dB for a perfect render. An empty mask gives NaN.
    """
    se = squared_errors(pred, ref)
    if mask is not None:
        m = _as_tensor(mask, "mask").bool()
        if m.shape != se.shape[:2]:
            raise ValueError(f"mask must be [H, W] = {tuple(se.shape[:2])}, got {tuple(m.shape)}")
        if not m.any():
            return float("nan")
        se = se[m]
    return mse_to_psnr(se.double().mean().item())


def ssim(pred, ref) -> float:
    """SSIM of pred [H, W, 3] against ref [H, W, 3] (RGB in [0, 1]).

    Implementation: ``pytorch_msssim.ssim`` (single-scale SSIM, not MS-SSIM) with data_range=1.0, its defaults
    11x11 Gaussian window with sigma 1.5, K = (0.01, 0.03), 'valid' filtering, averaged over channels and pixels.
    """
    from pytorch_msssim import ssim as _ssim

    p, r = _rgb_pair(pred, ref)
    x = p.permute(2, 0, 1)[None]
    y = r.permute(2, 0, 1)[None]
    return float(_ssim(x, y, data_range=1.0, size_average=True).item())


# --- LPIPS: only with locally present weights; never downloads --------------------------------------------------
_LPIPS_MODEL = None
_LPIPS_CHECKED = False
_ALEXNET_FILE = "alexnet-owt-7be5be79.pth"  # torchvision's AlexNet backbone that lpips(net='alex') loads


def _lpips_weights_present() -> bool:
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return False
    linear = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
    hub = Path(torch.hub.get_dir()) / "checkpoints" / _ALEXNET_FILE
    return linear.is_file() and hub.is_file()


def _lpips_model():
    global _LPIPS_MODEL, _LPIPS_CHECKED
    if _LPIPS_CHECKED:
        return _LPIPS_MODEL
    _LPIPS_CHECKED = True
    if os.environ.get("ELIGSIR_NO_LPIPS") or not _lpips_weights_present():
        return None
    try:
        import lpips

        _LPIPS_MODEL = lpips.LPIPS(net="alex", version="0.1", verbose=False).eval()
    except Exception:  # a broken install must not break evaluation: LPIPS is reported as null
        _LPIPS_MODEL = None
    return _LPIPS_MODEL


def lpips_available() -> bool:
    """True when LPIPS can be computed offline (package and both weight files present locally)."""
    return _lpips_model() is not None


def lpips_or_none(pred, ref) -> float | None:
    """LPIPS (AlexNet, v0.1) of pred [H, W, 3] vs ref [H, W, 3], or None when unavailable.

    Available only if the ``lpips`` package is installed AND both its linear-layer weights (shipped in the
    package) and torchvision's AlexNet checkpoint (in the torch hub cache, ``torch.hub.get_dir()``) are already on
    disk. Nothing is ever downloaded: otherwise this returns None (``metrics.json`` then holds ``null``).
    """
    model = _lpips_model()
    if model is None:
        return None
    p, r = _rgb_pair(pred, ref)
    with torch.no_grad():
        d = model(p.permute(2, 0, 1)[None], r.permute(2, 0, 1)[None], normalize=True)  # normalize: [0,1] -> [-1,1]
    return float(d.item())


# --- Depth ----------------------------------------------------------------------------------------------------
def depth_errors(pred_depth, ref_depth, max_depth: float | None = None) -> tuple[float, int]:
    """(sum of squared errors in m^2, number of scored pixels) under the masking policy of :func:`depth_rmse`."""
    r = _as_tensor(ref_depth, "ref_depth")
    p = _as_tensor(pred_depth, "pred_depth") if pred_depth is not None else torch.zeros_like(r)
    if p.shape != r.shape or r.ndim != 2:
        raise ValueError(f"depth maps must both be [H, W]; got pred {tuple(p.shape)} and ref {tuple(r.shape)}")
    valid = torch.isfinite(r) & (r > 0)
    if max_depth is not None:
        valid &= r <= max_depth
    p = torch.where(torch.isfinite(p), p, torch.zeros_like(p))  # a non-finite render is a missing render
    err = (p - r)[valid].double()
    return float(err.pow(2).sum().item()), int(valid.sum().item())


def depth_rmse(pred_depth, ref_depth, max_depth: float | None = None) -> float:
    """Depth RMSE in metres of pred [H, W] against ref [H, W] (metres, 0 = no measurement).

    Masking policy: a pixel is scored iff its reference depth is finite and > 0 (and <= ``max_depth`` when given).
    The prediction is never used to mask: a rendered depth of 0 (nothing rendered there) or a non-finite value is
    a missing render and is scored as 0 m, i.e. its error is the full reference depth. ``pred_depth=None`` scores
    the whole view as missing. Returns NaN when no pixel is scored.
    """
    sse, n = depth_errors(pred_depth, ref_depth, max_depth)
    return math.sqrt(sse / n) if n else float("nan")
