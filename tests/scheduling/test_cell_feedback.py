"""The views' error feedback through a per-view plan: the same running errors, bests and visits as folding each
render's sampled errors cell by cell; the fused (Triton, interpreted here) fold agrees with the torch rule."""

import pytest
import torch

from eligsir_o3d.scheduling.cell_feedback import fold_torch, make_plan
from eligsir_o3d.scheduling.microcells import MicrocellConfig, Microcells


def _by_hand(ids, errors, error, best, visits, ema):
    """The rule written out: each cell's observation is its samples' mean; EMA after the first visit; best from
    the second."""
    for c in sorted(set(ids.tolist()) - {-1}):
        obs = errors[ids == c].double().mean().item()
        e = obs if visits[c] == 0 else (1 - ema) * error[c].item() + ema * obs
        error[c] = e
        visits[c] += 1
        if visits[c] >= 2:
            best[c] = min(best[c].item(), e)


def _case(seed=0, n_pixels=300, samples=120, cells=9):
    g = torch.Generator().manual_seed(seed)
    pix = torch.randperm(n_pixels, generator=g)[:samples]
    ids = torch.randint(-1, cells, (samples,), generator=g)
    return pix, ids, cells


def test_plan_fold_follows_the_rule_over_several_renders():
    pix, ids, n = _case()
    plan = make_plan(pix, ids, 300, "cpu")
    error, best, visits = torch.full((n,), 0.15), torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long)
    e2, b2, v2 = error.clone().double(), best.clone().double(), visits.clone()
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        err = torch.rand(300, generator=g)
        fold_torch(plan, err, error, best, visits, 0.3)
        _by_hand(ids, err[pix], e2, b2, v2, 0.3)
        assert plan.last.item() == pytest.approx(err.mean().item())
    assert torch.equal(visits, v2)
    assert torch.allclose(error.double(), e2, atol=1e-6)
    finite = torch.isfinite(b2)
    assert torch.equal(torch.isfinite(best), finite) and torch.allclose(best.double()[finite], b2[finite], atol=1e-6)


def test_a_plan_without_cells_only_records_the_mean():
    plan = make_plan(torch.arange(4), torch.full((4,), -1), 10, "cpu")
    error = torch.zeros(0)
    fold_torch(plan, torch.ones(10), error, error.clone(), torch.zeros(0, dtype=torch.long), 0.3)
    assert plan.last.item() == 1.0


def test_the_fused_fold_agrees_with_the_torch_rule():
    pytest.importorskip("triton")
    from eligsir_o3d.kernels.triton_feedback import fold_cells
    from eligsir_o3d.kernels.triton_launch import counting

    pix, ids, n = _case(seed=3, n_pixels=2500, samples=700, cells=40)  # several blocks of pixels
    plans = [make_plan(pix, ids, 2500, "cpu") for _ in range(2)]
    state = [(torch.full((n,), 0.15), torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long))
             for _ in range(2)]
    g = torch.Generator().manual_seed(2)
    for _ in range(3):
        err = torch.rand(2500, generator=g)
        fold_torch(plans[0], err, *state[0], 0.3)
        with counting() as c:
            fold_cells(plans[1], err, *state[1], 0.3)
        assert c.n == 2
    (e0, b0, v0), (e1, b1, v1) = state
    assert torch.equal(v0, v1) and torch.allclose(e0, e1, atol=1e-6)
    assert torch.allclose(b0[torch.isfinite(b0)], b1[torch.isfinite(b1)], atol=1e-6)
    assert plans[1].last.item() == pytest.approx(plans[0].last.item(), abs=1e-6)
    assert not plans[1].scratch.any()  # zeroed for the next fold


def test_microcells_keep_their_statistics_on_a_device_and_read_them_on_the_host():
    cells = Microcells(MicrocellConfig())
    assert cells.host()[0] is cells.error  # a CPU map: no copy
    cells.error, cells.best = torch.tensor([0.2, 0.1]), torch.tensor([0.1, float("inf")])
    cells.visits, cells.coverage = torch.tensor([2, 0]), torch.zeros(2, dtype=torch.long)
    need = cells.need(torch.tensor([0, 1]), good_error=0.05, regress_gain=2.0, regress_margin=0.01)
    assert torch.allclose(need, torch.tensor([0.15 + 2.0 * 0.09, 0.05]))
    pix = cells.hash.lookup(torch.tensor([[0.1, 0.1, 1.0], [2.0, 0.1, 1.0]]))[0]  # two cells in the hash
    assert pix.tolist() == [0, 1]
    back = Microcells(MicrocellConfig()).to("cpu")
    back.load_state_dict(cells.state_dict())
    assert torch.equal(back.error, cells.error) and torch.equal(back.visits, cells.visits)


def test_the_numba_fold_is_the_torch_rule_bit_for_bit():
    from eligsir_o3d.kernels.cpu import NumbaKernels

    pix, ids, n = _case(seed=4, n_pixels=2500, samples=700, cells=40)
    plans = [make_plan(pix, ids, 2500, "cpu") for _ in range(2)]
    state = [(torch.full((n,), 0.15), torch.full((n,), float("inf")), torch.zeros(n, dtype=torch.long))
             for _ in range(2)]
    g = torch.Generator().manual_seed(5)
    for k in range(4):
        err = torch.rand(2500, generator=g)
        if k == 2:
            err[pix[:3]] = float("nan")  # a NaN observation becomes the cell's best, as torch.minimum has it
        fold_torch(plans[0], err, *state[0], 0.3)
        NumbaKernels.fold_cells(plans[1], err, *state[1], 0.3)
        for a, b in zip(*state):
            assert torch.equal(a, b) or torch.allclose(a, b, equal_nan=True, rtol=0, atol=0)
        assert plans[1].last.item() == pytest.approx(plans[0].last.item(), rel=1e-6, nan_ok=True)
        assert not plans[1].scratch.any()  # zeroed for the next fold
    assert (state[0][2] > 1).any()
