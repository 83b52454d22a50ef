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
    state_before = gm.optimizers["means"].state[gm.params["means"]]["exp_avg"].clone()
    new = gm.add(torch.zeros(7, 3), torch.rand(7, 3), torch.full((7,), 0.05), 0.3)
    assert len(gm) == 57 and new.tolist() == list(range(50, 57))
    gm.check_aligned()
    st = gm.optimizers["means"].state[gm.params["means"]]
    assert torch.equal(st["exp_avg"][:50], state_before)  # old moments kept
    assert st["exp_avg"][50:].abs().sum() == 0  # new ones start at zero
    mask = torch.zeros(57, dtype=torch.bool)
    mask[::3] = True
    kept_means = gm.means[~mask].detach().clone()
    gm.remove(mask)
    assert len(gm) == 57 - int(mask.sum())
    assert torch.equal(gm.means.detach(), kept_means)
    gm.check_aligned()
    _train_step(gm)  # Adam still works after resizing
    idx = torch.tensor([0, 2])
    gm.assign(idx, {"means": torch.ones(2, 3)})
    assert torch.equal(gm.means[idx].detach(), torch.ones(2, 3))
    assert gm.optimizers["means"].state[gm.params["means"]]["exp_avg"][idx].abs().sum() == 0
    gm.check_aligned()


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
