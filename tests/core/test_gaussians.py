"""GaussianMap invariants: parameters and Adam state stay aligned on add/remove/assign; PLY round trip."""

import numpy as np
import pytest
import torch

from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.io.ply import PlyError, load_ply, save_ply


def _filled(n=50, sh_degree=0, seed=0):
    g = torch.Generator().manual_seed(seed)
    gm = GaussianMap(sh_degree=sh_degree)
    gm.add(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), torch.rand(n, generator=g) * 0.1 + 0.01, 0.5)
    return gm


def _train_step(gm):
    loss = sum(p.pow(2).sum() for p in gm.params.values())
    gm.zero_grad()
    loss.backward()
    gm.step()


def test_add_remove_assign_keep_optimizer_aligned():
    gm = _filled(50)
    _train_step(gm)
    gm.check_aligned()
    state_before = gm.adam.exp_avg["means"].clone()
    new = gm.add(torch.zeros(7, 3), torch.rand(7, 3), torch.full((7,), 0.05), 0.3)
    assert len(gm) == 57 and new.tolist() == list(range(50, 57))
    gm.check_aligned()
    st = gm.adam.exp_avg["means"]
    assert torch.equal(st[:50], state_before)  # old moments kept
    assert st[50:].abs().sum() == 0 and gm.adam.exp_avg_sq["means"][50:].abs().sum() == 0  # new ones start at zero
    mask = torch.zeros(57, dtype=torch.bool)
    mask[::3] = True
    kept_means = gm.means[~mask].detach().clone()
    kept_moments = gm.adam.exp_avg_sq["sh0"][~mask].clone()
    gm.remove(mask)
    assert len(gm) == 57 - int(mask.sum())
    assert torch.equal(gm.means.detach(), kept_means) and torch.equal(gm.adam.exp_avg_sq["sh0"], kept_moments)
    gm.check_aligned()
    _train_step(gm)  # Adam still works after resizing
    idx = torch.tensor([0, 2])
    gm.assign(idx, {"means": torch.ones(2, 3)})
    assert torch.equal(gm.means[idx].detach(), torch.ones(2, 3))
    assert gm.adam.exp_avg["means"][idx].abs().sum() == 0 and gm.adam.exp_avg_sq["means"][idx].abs().sum() == 0
    gm.check_aligned()


def _sizes(gm):
    return {n: (tuple(p.shape), gm.adam.exp_avg[n].data_ptr(), p.data_ptr()) for n, p in gm.params.items()}


def test_parameters_and_moments_view_their_buffers():
    """params[name] is a Parameter over the first N rows of a buffer: autograd and the in-place step write there,
    and the moment rows past N stay zero through add, remove and growth."""
    gm = _filled(50, sh_degree=1)
    assert gm.capacity >= 50 and all(p.is_leaf and p.requires_grad for p in gm.params.values())
    _train_step(gm)
    assert gm.params["means"].grad.shape == (50, 3) and gm.adam.steps["means"] == 1
    gm.check_aligned()
    gm.add(torch.zeros(300, 3), torch.rand(300, 3), torch.full((300,), 0.05), 0.3)  # grows the buffers
    assert gm.capacity >= 350 and len(gm) == 350
    gm.check_aligned()
    gm.remove(torch.arange(350) % 2 == 0)
    gm.check_aligned()
    for bufs in gm._buffers.values():
        assert bufs[1][len(gm):].abs().sum() == 0 and bufs[2][len(gm):].abs().sum() == 0
    _train_step(gm)
    gm.check_aligned()


def test_add_writes_a_slice_without_copying_the_map():
    """Adding a small batch to a big map with room writes only the new rows: the buffers stay where they were, the
    rows already there are the same memory, and the new rows' moments are zero without a write."""
    gm = _filled(5000)
    gm.reserve(6000)
    _train_step(gm)
    ptrs = {n: (b[0].data_ptr(), b[1].data_ptr(), b[2].data_ptr()) for n, b in gm._buffers.items()}
    views = {n: gm.params[n].detach() for n in gm.params}  # the old rows, as views
    gm.add(torch.zeros(7, 3), torch.rand(7, 3), torch.full((7,), 0.05), 0.3)
    assert {n: (b[0].data_ptr(), b[1].data_ptr(), b[2].data_ptr()) for n, b in gm._buffers.items()} == ptrs
    for n, p in gm.params.items():
        assert p.data_ptr() == views[n].data_ptr() and torch.equal(p[:5000].detach(), views[n])
    gm.check_aligned()


VIEWS = {"slice", "select", "expand", "unsqueeze", "view", "alias", "detach", "lift_fresh", "as_strided"}


def _dispatched(fn) -> tuple[int, int]:
    """(torch operators that ``fn`` dispatches, those of them that compute: not a view)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    names = []

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            names.append(func.overloadpacket.__name__)
            return func(*args, **(kwargs or {}))

    with Count():
        fn()
    return len(names), sum(n not in VIEWS for n in names)


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_add_dispatches_a_few_operators_whatever_the_map_size(sh_degree):
    """The operators ``add`` dispatches do not grow with the map (no per-parameter concatenation of the map)."""
    counts = []
    for n in (1000, 100_000):
        gm = _filled(n, sh_degree)
        gm.reserve(n + 100)
        g = torch.Generator().manual_seed(1)
        means, rgbs = torch.randn(20, 3, generator=g), torch.rand(20, 3, generator=g)
        counts.append(_dispatched(lambda: gm.add(means, rgbs, torch.full((20,), 0.05), 0.3)))
        gm.check_aligned()
    assert counts[0] == counts[1], counts
    assert counts[0][0] <= 48 and counts[0][1] <= 14, counts  # 24 of the operators are the rows' views


def test_map_adam_is_torch_adam():
    """MapAdam's map-wide step (compiled on float32 CPU tensors, torch operators otherwise) ends where one
    torch.optim.Adam per parameter ends, with the same moments and step counts, also after a learning-rate change
    and with parameters that get no gradient."""
    from eligsir_o3d.optim.adam import AdamConfig, MapAdam

    g = torch.Generator().manual_seed(0)
    shapes = {"means": (40, 3), "opacities": (40,), "shN": (40, 3, 3)}
    for dtype in (torch.float32, torch.float64):  # float64: the torch path
        init = {n: torch.randn(s, generator=g, dtype=dtype) for n, s in shapes.items()}
        ours = {n: torch.nn.Parameter(t.clone()) for n, t in init.items()}
        ref = {n: torch.nn.Parameter(t.clone()) for n, t in init.items()}
        lrs = {"means": 1e-2, "opacities": 5e-2, "shN": 1e-3}
        adam = MapAdam(lrs, AdamConfig(beta2=0.99))
        adam.exp_avg = {n: torch.zeros_like(t) for n, t in init.items()}
        adam.exp_avg_sq = {n: torch.zeros_like(t) for n, t in init.items()}
        opts = {n: torch.optim.Adam([p], lr=lrs[n], betas=(0.9, 0.99), eps=1e-15, foreach=False)
                for n, p in ref.items()}
        for k in range(6):
            target = {n: torch.randn(s, generator=g, dtype=dtype) for n, s in shapes.items()}
            skip = "opacities" if k == 2 else None
            if k == 3:
                adam.lr["means"] = opts["means"].param_groups[0]["lr"] = 3e-3
            for params in (ours, ref):
                for n, p in params.items():
                    p.grad = None if n == skip else 2 * (p.detach() - target[n]) * (1 + k)
            adam.step_map(ours, {n: p.grad for n, p in ours.items()})
            for n, o in opts.items():
                if n != skip:
                    o.step()
        for n, p in ours.items():
            tol = dict(rtol=1e-6, atol=1e-7) if dtype == torch.float32 else dict(rtol=0, atol=0)
            st = opts[n].state[ref[n]]
            torch.testing.assert_close(p.detach(), ref[n].detach(), **tol)
            torch.testing.assert_close(adam.exp_avg[n], st["exp_avg"], **tol)
            torch.testing.assert_close(adam.exp_avg_sq[n], st["exp_avg_sq"], **tol)
            assert adam.steps[n] == int(st["step"]) == (5 if n == "opacities" else 6)


def test_map_state_round_trip():
    """state_dict/load_state_dict keep parameters, moments, step counts and learning rates; a PLY-like state
    without Adam starts fresh."""
    gm = _filled(30, sh_degree=1)
    _train_step(gm)
    gm.adam.lr["means"] = 1e-5
    back = GaussianMap(sh_degree=1)
    back.load_state_dict(gm.state_dict())
    back.check_aligned()
    assert back.adam.steps == gm.adam.steps and back.adam.lr == gm.adam.lr
    for n in gm.params:
        assert torch.equal(back.params[n].detach(), gm.params[n].detach())
        assert torch.equal(back.adam.exp_avg_sq[n], gm.adam.exp_avg_sq[n])
    _train_step(gm)
    _train_step(back)
    assert torch.equal(back.means.detach(), gm.means.detach())
    fresh = GaussianMap(sh_degree=1)
    fresh.load_state_dict({k: v for k, v in gm.state_dict().items() if k != "adam"})
    assert fresh.adam.steps["means"] == 0 and fresh.adam.exp_avg["means"].abs().sum() == 0


def test_activations():
    gm = GaussianMap()
    gm.add(torch.zeros(1, 3), torch.tensor([[0.2, 0.4, 0.6]]), torch.tensor([0.03]), 0.7)
    assert torch.allclose(gm.scales, torch.full((1, 3), 0.03))
    assert torch.allclose(gm.opacities, torch.tensor([0.7]))
    assert torch.allclose(gm.colors(), torch.tensor([[0.2, 0.4, 0.6]]), atol=1e-6)


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_ply_round_trip(tmp_path, sh_degree):
    gm = _filled(40, sh_degree)
    with torch.no_grad():
        gm.params["shN"].normal_()
    path = save_ply(gm, tmp_path / "map.ply")
    back = load_ply(path)
    assert back.sh_degree == sh_degree
    for name, p in gm.params.items():
        torch.testing.assert_close(back.params[name], p.detach(), rtol=0, atol=0)
    assert not (tmp_path / "map.ply.tmp").exists()


def test_ply_read_by_plyfile_has_3dgs_fields(tmp_path):
    from plyfile import PlyData

    gm = _filled(10)
    v = PlyData.read(str(save_ply(gm, tmp_path / "m.ply")))["vertex"]
    for f in ["x", "y", "z", "nx", "f_dc_0", "opacity", "scale_2", "rot_3"]:
        assert f in v.data.dtype.names
    np.testing.assert_allclose(v["opacity"], gm.params["opacities"].detach().numpy())


def test_ply_missing_attributes_is_a_clear_error(tmp_path):
    from plyfile import PlyData, PlyElement

    arr = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "pts.ply"))
    with pytest.raises(PlyError, match="missing vertex properties.*f_dc_0"):
        load_ply(tmp_path / "pts.ply")
    with pytest.raises(PlyError, match="no such file"):
        load_ply(tmp_path / "absent.ply")
