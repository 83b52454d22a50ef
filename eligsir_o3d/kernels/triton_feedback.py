""":func:`eligsir_o3d.scheduling.cell_feedback.fold_torch` in Triton: two launches, no host synchronisation.

The first runs over the error map's pixels: each sampled pixel adds its error to its cell's slot of the plan's
scratch, and every block adds its pixels' sum to the scratch's last slot (atomic adds: the sums' order, and so
their last bits, may differ from the reference's). The second runs over the plan's cells: the observation, the
running error, visits and best error of each cell, the scratch zeroed for the next fold, and the map's mean error
into ``plan.last``.
"""

from __future__ import annotations

import torch
import triton.language as tl

from .triton_launch import cdiv, kernel, launch

BLOCK = 1024


@kernel
def _splat_kernel(err_ptr, pixel_cell_ptr, scratch_ptr, P, C, BLOCK: tl.constexpr):
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    ok = r < P
    e = tl.load(err_ptr + r, mask=ok, other=0.0)
    c = tl.load(pixel_cell_ptr + r, mask=ok, other=-1)
    tl.atomic_add(scratch_ptr + c, e, mask=ok & (c >= 0))
    tl.atomic_add(scratch_ptr + C, tl.sum(e, 0))


@kernel
def _fold_kernel(scratch_ptr, counts_ptr, cells_ptr, error_ptr, best_ptr, visits_ptr, last_ptr, C, P, ema,
                 BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    r = pid * BLOCK + tl.arange(0, BLOCK)
    ok = r < C
    obs = tl.load(scratch_ptr + r, mask=ok, other=0.0) / tl.load(counts_ptr + r, mask=ok, other=1.0)
    cell = tl.load(cells_ptr + r, mask=ok, other=0)
    v = tl.load(visits_ptr + cell, mask=ok, other=0)
    e = tl.load(error_ptr + cell, mask=ok, other=0.0)
    b = tl.load(best_ptr + cell, mask=ok, other=0.0)
    e_new = tl.where(v == 0, obs, (1 - ema) * e + ema * obs)
    v_new = v + 1
    b_new = tl.where(v_new >= 2, tl.minimum(b, e_new), b)
    tl.store(error_ptr + cell, e_new, mask=ok)
    tl.store(visits_ptr + cell, v_new, mask=ok)
    tl.store(best_ptr + cell, b_new, mask=ok)
    tl.store(scratch_ptr + r, tl.zeros([BLOCK], dtype=tl.float32), mask=ok)
    if pid == 0:
        tl.store(last_ptr, tl.load(scratch_ptr + C) / P)
        tl.store(scratch_ptr + C, 0.0)


def fold_cells(plan, error_map: torch.Tensor, error: torch.Tensor, best: torch.Tensor, visits: torch.Tensor,
               ema: float) -> None:
    """The fold of :func:`eligsir_o3d.scheduling.cell_feedback.fold_torch` (same arguments) in two launches."""
    P, C = plan.n_pixels, int(plan.cells.numel())
    error_map = error_map.contiguous()
    launch(_splat_kernel, (cdiv(P, BLOCK),), error_map, plan.pixel_cell, plan.scratch, P, C, BLOCK=BLOCK)
    launch(_fold_kernel, (max(1, cdiv(C, BLOCK)),), plan.scratch, plan.counts, plan.cells, error, best,
           visits, plan.last, C, P, float(ema), BLOCK=BLOCK)
