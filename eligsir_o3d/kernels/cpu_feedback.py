""":func:`eligsir_o3d.scheduling.cell_feedback.fold_torch` as one serial numba pass over a view's samples and cells.

The arithmetic of the reference: per-cell sums in sample order in float32, the observation, the running error's
float32 EMA, visits and the settled best, so the cells' statistics keep their bits. The map's mean error
(``plan.last``, kept for the saved state only) is summed in float64. Compiled lazily on first use and cached on
disk like the renderer's kernels.
"""

from __future__ import annotations

import numpy as np

from ..runtime.jit import jit_serial as _jit_serial


@_jit_serial
def fold_samples(err, pix, inv, cells, counts, sums, ema, error, best, visits, last):
    """err [P] float32; samples at pixels ``pix`` [M] in slots ``inv`` [M] of ``cells`` [C] (ids, ascending) with
    ``counts`` [C] samples each; ``sums`` [C + 1] float32 zeros, left zero. Per cell the mean error obs, then
    error = obs on a first visit else (1 - ema) error + ema obs, visits += 1, and from the second visit
    best = min(best, error) (NaN kept); last[0] = the mean of ``err``."""
    total = 0.0
    for k in range(err.shape[0]):
        total += err[k]
    last[0] = np.float32(total / max(err.shape[0], 1))
    for k in range(pix.shape[0]):
        sums[inv[k]] += err[pix[k]]
    keep, a = np.float32(1.0 - ema), np.float32(ema)
    for c in range(cells.shape[0]):
        cid = cells[c]
        obs = sums[c] / counts[c]
        sums[c] = np.float32(0.0)
        e = obs if visits[cid] == 0 else keep * error[cid] + a * obs
        error[cid] = e
        visits[cid] += 1
        if visits[cid] >= 2:
            b = best[cid]
            best[cid] = e if (e < b or np.isnan(e)) else b
