"""Evaluation protocol of the paper: held-out image metrics, regional quality (CVQ, CUC@Q, CVQ-AUC), plots, tables.

Everything here is independent of the mapper: it sees only held-out frames, released source frames and a
``render_fn(frame) -> RenderOutput | None``. matplotlib is imported only when plots are written.
"""

from .compare import compare_results
from .heldout import HeldoutEvaluator
from .metrics import EPS, PSNR_CAP, depth_rmse, lpips_available, lpips_or_none, mse_to_psnr, psnr, ssim
from .plots import write_plots
from .regional import RegionalQuality, cvq_auc

__all__ = [
    "EPS",
    "PSNR_CAP",
    "HeldoutEvaluator",
    "RegionalQuality",
    "compare_results",
    "cvq_auc",
    "depth_rmse",
    "lpips_available",
    "lpips_or_none",
    "mse_to_psnr",
    "psnr",
    "ssim",
    "write_plots",
]
