"""Numba kernel of :meth:`.microcells.Microcells.accumulate_samples` on the CPU: one training render's per-pixel
error folded into its view's cells in one serial pass, the arithmetic of :meth:`.microcells.Microcells.accumulate`
(sums in sample order, float32 EMA, visits, the settled best), so the cells' statistics keep their bits.
Compiled lazily on first use and cached on disk like the renderer's kernels."""

from __future__ import annotations

import numpy as np

from ..runtime.jit import jit_serial as _jit_serial


@_jit_serial
def fold_cells(err, pix, inv, cells, counts, ema, error, best, visits):
    """err [H W] float32 (flat), samples at pixels ``pix`` [K] in cell slots ``inv`` [K] of ``cells`` [C] (ids,
    ascending) with ``counts`` [C] float32 samples each; per cell the mean error obs, then error = obs on a first
    visit else (1 - ema) error + ema obs, visits += 1, and from the second visit best = min(best, error)."""
    sums = np.zeros(cells.shape[0], np.float32)
    for k in range(pix.shape[0]):
        sums[inv[k]] += err[pix[k]]
    keep, a = np.float32(1.0 - ema), np.float32(ema)
    for c in range(cells.shape[0]):
        cid = cells[c]
        obs = sums[c] / counts[c]
        e = obs if visits[cid] == 0 else keep * error[cid] + a * obs
        error[cid] = e
        visits[cid] += 1
        if visits[cid] >= 2:
            b = best[cid]
            best[cid] = e if (e < b or np.isnan(e)) else b
