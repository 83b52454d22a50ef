"""The compiled per-update work outside the renderer: the map's Adam step (eligsir_o3d/optim/adam.py) is torch's
Adam (values to float32 rounding, the same moments and step counts), and the MCMC noise
(eligsir_o3d/optim/update_kernels.py) is the torch formula's."""

import pytest
import torch

from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.render.projection import quat_to_rotmat
from eligsir_o3d.scheduling.mcmc import inject_noise


def _map(n=300, seed=0, sh_degree=1):
    g = torch.Generator().manual_seed(seed)
    gmap = GaussianMap(sh_degree)
    gmap.add(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), 0.01 + 0.05 * torch.rand(n, generator=g),
             0.05 + 0.9 * torch.rand(n, generator=g),
             torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))
    return gmap


def _loss(gmap, k):
    g = torch.Generator().manual_seed(100 + k)
    return sum(((p - torch.randn(p.shape, generator=g)) ** 2 * (1 + k)).sum() for p in gmap.params.values())


def _torch_adams(gmap):
    a = gmap.adam
    return {n: torch.optim.Adam([p], lr=a.lr[n], betas=(a.beta1, a.beta2), eps=a.eps, foreach=False)
            for n, p in gmap.params.items()}


@pytest.mark.parametrize("steps", [1, 7])
def test_map_step_is_torch_adam(steps):
    ours, ref = _map(), _map()
    opts = _torch_adams(ref)
    for k in range(steps):
        for gm in (ours, ref):
            gm.zero_grad()
            _loss(gm, k).backward()
        ours.step()
        for opt in opts.values():
            opt.step()
    for name, p in ours.params.items():
        torch.testing.assert_close(p.detach(), ref.params[name].detach(), rtol=1e-5, atol=1e-6)
        r = opts[name].state[ref.params[name]]
        assert ours.adam.steps[name] == int(r["step"]) == steps
        torch.testing.assert_close(ours.adam.exp_avg[name], r["exp_avg"], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(ours.adam.exp_avg_sq[name], r["exp_avg_sq"], rtol=1e-5, atol=1e-9)


def test_map_step_skips_what_torch_skips_and_follows_the_learning_rate():
    gmap, ref = _map(sh_degree=0), _map(sh_degree=0)
    gmap.adam.lr["means"] *= 3  # a schedule's change reaches the step
    opts = _torch_adams(ref)
    opts["means"].param_groups[0]["lr"] *= 3
    for gm in (gmap, ref):
        gm.params["means"].grad = torch.ones_like(gm.params["means"])  # only the means have a gradient
    before = {n: p.detach().clone() for n, p in gmap.params.items()}
    gmap.step()
    opts["means"].step()
    torch.testing.assert_close(gmap.means.detach(), ref.means.detach(), rtol=1e-6, atol=1e-7)
    assert not torch.equal(gmap.means.detach(), before["means"])
    for name in ("scales", "quats", "opacities", "sh0"):
        assert torch.equal(gmap.params[name].detach(), before[name]) and gmap.adam.steps[name] == 0


def test_compiled_noise_is_the_torch_formula():
    gmap = _map(500, sh_degree=0)
    with torch.no_grad():
        gmap.params["opacities"][:250] = torch.logit(torch.full((250,), 0.002))  # transparent: these move
    before = gmap.means.detach().clone()
    z = torch.randn(500, 3, generator=torch.Generator().manual_seed(7))
    o = gmap.opacities.detach()
    M = quat_to_rotmat(gmap.quats.detach()) * gmap.scales.detach()[:, None, :]
    want = torch.einsum("nij,nj->ni", M @ M.transpose(1, 2), z) * (torch.sigmoid(100.0 * ((1.0 - o) - 0.995)) * 250.0)[:, None]
    inject_noise(gmap, 250.0, torch.Generator().manual_seed(7))
    torch.testing.assert_close(gmap.means.detach(), before + want, rtol=1e-6, atol=2e-7)  # float32 rounding
    assert want[:250].norm(dim=1).min() > 1e-5  # the transparent ones moved visibly


@pytest.mark.parametrize("n_rows", [0, 37, 500])
def test_noise_on_a_views_rows_is_the_torch_formula_there_and_nothing_elsewhere(n_rows):
    gmap = _map(500, sh_degree=0)
    with torch.no_grad():
        gmap.params["opacities"][::3] = torch.logit(torch.full((167,), 0.002))  # transparent: these move
    rows = torch.randperm(500, generator=torch.Generator().manual_seed(3))[:n_rows].sort().values
    before = gmap.means.detach().clone()
    z = torch.randn(n_rows, 3, generator=torch.Generator().manual_seed(7))
    o = gmap.opacities.detach()[rows]
    M = quat_to_rotmat(gmap.quats.detach()[rows]) * gmap.scales.detach()[rows][:, None, :]
    want = torch.einsum("nij,nj->ni", M @ M.transpose(1, 2), z) * (torch.sigmoid(100.0 * ((1.0 - o) - 0.995)) * 250.0)[:, None]
    inject_noise(gmap, 250.0, torch.Generator().manual_seed(7), rows=rows)
    after = gmap.means.detach()
    torch.testing.assert_close(after[rows], before[rows] + want, rtol=1e-6, atol=2e-7)  # float32 rounding
    others = torch.ones(500, dtype=torch.bool)
    others[rows] = False
    assert torch.equal(after[others], before[others])  # rows out of the view: bit for bit
    if n_rows == 500:
        assert want[::3].norm(dim=1).min() > 1e-5  # the transparent ones moved visibly
