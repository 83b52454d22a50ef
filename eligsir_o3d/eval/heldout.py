"""HeldoutEvaluator: the paper's held-out evaluation during and after mapping.

The pipeline owns the split (which frames are held out) and the clocks; this object owns what is measured:
- ``observe_source(frame)`` whenever a source frame is RELEASED to the mapper (drives regional eligibility);
- ``checkpoint(render_fn, ...)`` every N optimisation updates: held-out PSNR / SSIM / depth RMSE and CVQ, CUC@Q,
  one record appended to ``curve``;
- ``final(render_fn)`` on the evaluated map state: the full metrics including LPIPS, CVQ-AUC and the cell table.

Evaluation time is kept out of mapping time: every call above runs inside :meth:`timed`, which adds its wall time
to ``eval_seconds`` (on CUDA it first synchronises, so that mapper kernels still in flight are not billed to
evaluation). The pipeline subtracts ``eval_seconds`` from its mapping clock, or uses :meth:`timed` for its own
evaluation work.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from typing import Callable

import numpy as np
import torch

from ..core.frame import Frame
from .metrics import MISSING, depth_errors, lpips_available, lpips_or_none, psnr, ssim
from .regional import RegionalQuality, cvq_auc

NEAR_DEPTH_M = 2.0  # depth RMSE is also reported restricted to reference depth <= 2 m


def _finite_or_none(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _sync() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def up_axis(frames: list[Frame]) -> int:
    """World axis closest to 'up' as seen by the cameras (OpenCV y points down): used for top-down plots."""
    if not frames:
        return 2
    down = np.mean([np.asarray(f.T_world_cam)[:3, 1] for f in frames], axis=0)
    return int(np.argmax(np.abs(down)))


class HeldoutEvaluator:
    """Held-out image metrics and regional quality (CVQ, CUC@Q, CVQ-AUC) of one run; independent of the mapper."""

    def __init__(self, heldout_frames: list[Frame], cell_size: float = 0.5, min_samples: int = 300,
                 min_views: int = 2, quality_threshold: float = 20.0, sample_stride: int = 4, *,
                 min_source_views: int = 2, source_stride: int | None = None, checkpoint_ssim: bool = True):
        # no held-out frame (a recording shorter than the held-out period, --holdout-every 0): the run is evaluated
        # on nothing, and every held-out figure is None ("no held-out figure"), not an error
        self.eval_seconds = 0.0
        self.frames = list(heldout_frames)
        self.quality_threshold = float(quality_threshold)
        self.checkpoint_ssim = checkpoint_ssim
        self.curve: list[dict] = []
        with self.timed():
            self.regional = RegionalQuality(self.frames, cell_size, min_samples, min_views, quality_threshold,
                                            sample_stride, min_source_views, source_stride)
        self.up_axis = up_axis(self.frames)

    @contextmanager
    def timed(self):
        """Add the wall time of the block to ``eval_seconds`` (evaluation is excluded from mapping time)."""
        _sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            _sync()
            self.eval_seconds += time.perf_counter() - t0

    def observe_source(self, frame: Frame) -> bool:
        """A source frame was released to the mapper; held-out frames are ignored (returns False)."""
        with self.timed():
            return self.regional.observe_source(frame)

    # --- rendering and per-view scores ---------------------------------------------------------------------------
    def _score_views(self, render_fn: Callable, with_lpips: bool, with_ssim: bool,
                     regional: bool = False) -> tuple[list[dict], dict | None, dict]:
        """(per-view scores, regional summary or None, aggregate). One view at a time: its reference images are
        decoded (a :class:`~eligsir_o3d.eval.heldout_view.HeldoutView` is stored compactly), scored, its render
        added to the regional accumulators, and all of it dropped before the next view is rendered."""
        views = []
        sse_all = n_all = sse_near = n_near = 0.0
        acc = self.regional.begin() if regional else None
        with torch.no_grad():
            for k, f in enumerate(self.frames):
                out = render_fn(f)
                color = None if out is None else getattr(out, "color", None)
                depth = None if out is None else getattr(out, "depth", None)
                del out
                color = None if color is None else color.detach().to("cpu", torch.float32)
                depth = None if depth is None else depth.detach().to("cpu", torch.float32)
                ref_color, ref_depth = f.decoded()  # float32 [H, W, 3] and [H, W], for this view only
                v = {"index": int(f.index), "timestamp": float(f.timestamp), "missing": color is None}
                if color is None:
                    v["psnr"] = MISSING["psnr"]
                    v["ssim"] = MISSING["ssim"] if with_ssim else None
                    v["lpips"] = MISSING["lpips"] if with_lpips and lpips_available() else None
                else:
                    if color.shape != ref_color.shape:
                        raise ValueError(f"held-out view {f.index}: render is {tuple(color.shape)}, "
                                         f"reference is {tuple(ref_color.shape)}")
                    v["psnr"] = psnr(color, ref_color)
                    v["ssim"] = ssim(color, ref_color) if with_ssim else None
                    v["lpips"] = lpips_or_none(color, ref_color) if with_lpips else None
                sse, n = depth_errors(depth, ref_depth)
                sse2, n2 = depth_errors(depth, ref_depth, NEAR_DEPTH_M)
                v["depth_rmse_m"] = _finite_or_none(math.sqrt(sse / n) if n else float("nan"))
                v["depth_rmse_2m_m"] = _finite_or_none(math.sqrt(sse2 / n2) if n2 else float("nan"))
                sse_all, n_all, sse_near, n_near = sse_all + sse, n_all + n, sse_near + sse2, n_near + n2
                if acc is not None:
                    s_c, n_c = self.regional.accumulate(k, color, ref_color, ref_depth)
                    acc[0].add_(s_c)
                    acc[1].add_(n_c)
                views.append(v)
                del color, depth, ref_color, ref_depth
        reg = self.regional.finish(*acc) if acc is not None else None
        if not views:
            return views, reg, {"psnr": None, "ssim": None, "lpips": None, "depth_rmse_m": None,
                                   "depth_rmse_2m_m": None, "missing_views": 0}
        agg = {
            "psnr": float(np.mean([v["psnr"] for v in views])),
            "ssim": float(np.mean([v["ssim"] for v in views])) if with_ssim else None,
            "lpips": (float(np.mean([v["lpips"] for v in views]))
                      if with_lpips and all(v["lpips"] is not None for v in views) else None),
            # pooled over every scored pixel of every held-out view (not a mean of per-view RMSEs)
            "depth_rmse_m": math.sqrt(sse_all / n_all) if n_all else None,
            "depth_rmse_2m_m": math.sqrt(sse_near / n_near) if n_near else None,
            "missing_views": sum(v["missing"] for v in views),
        }
        return views, reg, agg

    def scores(self, render_fn: Callable) -> dict:
        """Mean held-out PSNR and SSIM of ``render_fn`` (no curve record, no regional quality)."""
        with self.timed():
            _, _, agg = self._score_views(render_fn, with_lpips=False, with_ssim=True)  # no regional update
        return {"psnr": agg["psnr"], "ssim": agg["ssim"]}

    # --- during mapping ------------------------------------------------------------------------------------------
    def checkpoint(self, render_fn: Callable, *, t_s: float, progress: float, updates: int,
                   supervised_mpix: float, gaussians: int, extra: dict | None = None) -> dict:
        """Render every held-out view with ``render_fn(frame) -> RenderOutput | None`` and append one curve record.

        The render needs ``.color`` [H, W, 3] in [0, 1] and ``.depth`` [H, W] metres at the frame's own resolution
        (any device). None, or ``.color`` None, is a missing render (a failure); ``.depth`` None scores depth as
        missing only.

        t_s: elapsed mapping time (evaluation excluded); progress: N_released / N_total of source frames.
        The record holds t_s, progress, updates, psnr, ssim, depth_rmse_m, depth_rmse_2m_m, cvq, cuc20 (None while
        M(t) is empty), n_eligible, n_measurable, n_evaluable (|M(t)|), supervised_mpix, gaussians, eval_s, plus
        ``extra``.
        """
        before = self.eval_seconds
        with self.timed():
            _, reg, agg = self._score_views(render_fn, with_lpips=False, with_ssim=self.checkpoint_ssim,
                                            regional=True)
        rec = {
            "t_s": float(t_s), "progress": float(progress), "updates": int(updates),
            "psnr": agg["psnr"], "ssim": agg["ssim"], "depth_rmse_m": agg["depth_rmse_m"],
            "depth_rmse_2m_m": agg["depth_rmse_2m_m"], "missing_views": agg["missing_views"],
            "cvq": reg["cvq"], "cuc20": reg["cuc"], "n_eligible": reg["n_eligible"],
            "n_measurable": reg["n_measurable"], "n_evaluable": reg["n_evaluable"],
            "supervised_mpix": float(supervised_mpix), "gaussians": int(gaussians),
            "eval_s": self.eval_seconds - before,
        }
        if extra:
            rec.update(extra)
        self.curve.append(rec)
        return rec

    def auc(self) -> float | None:
        """CVQ-AUC of the curve so far (see :func:`cvq_auc`)."""
        return cvq_auc([r["progress"] for r in self.curve], [r["cvq"] for r in self.curve])

    # --- evaluated map state -------------------------------------------------------------------------------------
    def final(self, render_fn: Callable) -> dict:
        """Full held-out metrics of the evaluated map state (ME or +N PM).

        Returns psnr, ssim, lpips (None unless available locally), depth_rmse_m, depth_rmse_2m_m (pooled over valid
        reference pixels), per_view (list of dicts), cvq_final, cuc20_final (regional quality of this state; a
        final eligibility update counts every source frame observed so far), cvq_auc (over ``curve``: call
        :meth:`checkpoint` once at the end of the stream so that the curve reaches p = 1), n_* cell counts,
        cells (the table for the top-down plot) and eval_seconds (total, this call included).
        """
        with self.timed():
            views, reg, agg = self._score_views(render_fn, with_lpips=True, with_ssim=True, regional=True)
        return {
            "psnr": agg["psnr"], "ssim": agg["ssim"], "lpips": agg["lpips"],
            "depth_rmse_m": agg["depth_rmse_m"], "depth_rmse_2m_m": agg["depth_rmse_2m_m"],
            "missing_views": agg["missing_views"], "n_views": len(views), "per_view": views,
            "cvq_final": reg["cvq"], "cuc20_final": reg["cuc"], "cvq_auc": self.auc(),
            "n_cells": reg["n_cells"], "n_eligible": reg["n_eligible"], "n_measurable": reg["n_measurable"],
            "n_evaluable": reg["n_evaluable"], "cells": self.regional.cell_table(self.up_axis),
            "eval_seconds": self.eval_seconds,
        }
