"""A training render's error folded into the microcells, where the map lives.

Which pixels of a view fall in which microcells is fixed per view and resolution: a :class:`FeedbackPlan` made
once on the host (the cells' hash is Open3D's, on the CPU) and kept on the map's device. Folding one error map
into the cells is then device work without a host synchronisation: :func:`fold_torch` in torch operators (the
rule, and the oracle of the fused kernel of :mod:`eligsir_o3d.kernels.triton_feedback`).

The rule: a cell's observation is the mean error of its samples in the map; a cell never measured takes it, a
measured one moves ``ema`` of the way towards it; visits count the folds; the best running error follows the cell
from its second visit, so that one lucky first sample is not its reference. ``plan.last`` holds the mean error of
the whole map last folded.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class FeedbackPlan:
    """The samples of one view at one resolution that fall in a cell (all tensors on the map's device)."""

    pix: torch.Tensor  # [M] int64 flat pixel index of each sample, in sample order
    inv: torch.Tensor  # [M] int64 index into ``cells`` of each sample
    cells: torch.Tensor  # [C] int64 the cells' ids, ascending
    counts: torch.Tensor  # [C] float32 samples per cell
    pixel_cell: torch.Tensor  # [P] int32 per pixel: index into ``cells`` of its sample, -1 for none
    scratch: torch.Tensor  # [C + 1] float32 zeros between folds: per-cell sums and the map's total
    last: torch.Tensor  # [1] float32 the mean error of the map last folded (NaN before the first)
    n_pixels: int


def make_plan(pix: torch.Tensor, ids: torch.Tensor, n_pixels: int, device) -> FeedbackPlan:
    """The plan of samples at flat pixels ``pix`` [M] in cells ``ids`` [M] (-1: no cell) of an ``n_pixels`` map."""
    keep = ids >= 0
    pix, ids = pix[keep].long(), ids[keep].long()
    cells, inv = torch.unique(ids, return_inverse=True)
    counts = torch.bincount(inv, minlength=cells.numel()).float()
    pixel_cell = torch.full((n_pixels,), -1, dtype=torch.int32)
    pixel_cell[pix] = inv.to(torch.int32)
    dev = torch.device(device)
    return FeedbackPlan(pix.to(dev), inv.to(dev), cells.to(dev), counts.to(dev), pixel_cell.to(dev),
                        torch.zeros(cells.numel() + 1, device=dev), torch.full((1,), float("nan"), device=dev),
                        int(n_pixels))


def fold_torch(plan: FeedbackPlan, error_map: torch.Tensor, error: torch.Tensor, best: torch.Tensor,
               visits: torch.Tensor, ema: float) -> None:
    """Fold ``error_map`` [P] (flat, on the plan's device) into the cells' ``error``, ``best`` and ``visits``."""
    plan.last.copy_(error_map.mean())
    if plan.cells.numel() == 0:
        return
    cells = plan.cells
    sums = torch.zeros(cells.numel(), device=error_map.device).index_add_(0, plan.inv, error_map[plan.pix])
    obs = sums / plan.counts
    fresh = visits[cells] == 0
    error[cells] = torch.where(fresh, obs, (1 - ema) * error[cells] + ema * obs)
    visits[cells] += 1
    settled = visits[cells] >= 2
    best[cells] = torch.where(settled, torch.minimum(best[cells], error[cells]), best[cells])
