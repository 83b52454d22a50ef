"""Microcells.accumulate_samples (one compiled pass on the CPU) keeps accumulate's values bit for bit: running
error, best and visits over repeated folds of the same view's samples and of a second view's."""

import torch

from eligsir_o3d.scheduling.microcells import Microcells


def _cells(n=50):
    mc = Microcells()
    mc.error = torch.full((n,), mc.cfg.init_error)
    mc.best = torch.full((n,), float("inf"))
    mc.visits = torch.zeros(n, dtype=torch.long)
    return mc


def test_accumulate_samples_is_accumulate_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    views = []
    for m in (300, 120):
        pix = torch.randperm(40 * 30, generator=g)[:m]
        ids = torch.randint(-1, 50, (m,), generator=g)
        views.append((pix, ids))
    fast, slow = _cells(), _cells()
    for step in range(6):
        pix, ids = views[step % 2]
        err = torch.rand(40 * 30, generator=g) * 0.5
        fast.accumulate_samples(pix, ids, err)
        slow.accumulate(ids, err[pix])
        for name in ("error", "best", "visits"):
            assert torch.equal(getattr(fast, name), getattr(slow, name)), (step, name)
    assert (fast.visits > 1).any() and torch.isfinite(fast.best).any()


def test_accumulate_samples_without_inserted_cells_changes_nothing():
    mc = _cells(5)
    mc.accumulate_samples(torch.arange(4), torch.full((4,), -1), torch.rand(4))
    assert not mc.visits.any()
