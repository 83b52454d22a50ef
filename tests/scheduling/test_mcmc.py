"""3DGS-MCMC in torch: the closed-form relocation, relocation/densification with aligned optimizer state, the cap."""

import copy
import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.render import get_renderer
from eligsir_o3d.scheduling.mcmc import MCMCConfig, MCMCRefiner, inject_noise, relocate, relocation_params, sample_add

CAM = Camera(32, 32, 40.0, 40.0, 16.0, 16.0)  # the test Gaussian projects onto pixel (16, 16)


def _map(opacities, spread=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = len(opacities)
    gmap = GaussianMap(1)  # one SH band, so copies must carry shN too
    means = torch.tensor([[0.0, 0.0, 2.0]]).repeat(n, 1) + spread * torch.randn(n, 3, generator=g)
    gmap.add(means, torch.rand(n, 3, generator=g), torch.full((n,), 0.05), torch.tensor(opacities))
    with torch.no_grad():
        gmap.params["shN"].normal_(0, 0.1, generator=g)
    return gmap


def _adam_steps(gmap, k=3):
    for _ in range(k):
        gmap.zero_grad()
        loss = sum((p * p).sum() for p in gmap.params.values())
        loss.backward()
        gmap.step()


def _exact_D(o_new: Fraction, n: int) -> float:
    """D with exact rationals except the 1/sqrt(j) factors (evaluated per term in float)."""
    return float(sum(Fraction(math.comb(n, j)) * (-1) ** (j - 1) * o_new ** j / Fraction(math.sqrt(j))
                     for j in range(1, n + 1)))


@pytest.mark.parametrize("n", [1, 2, 5, 17, 51])
@pytest.mark.parametrize("o", [0.02, 0.5, 0.97])
def test_closed_form_relocation(n, o):
    scales = torch.tensor([[0.1, 0.2, 0.3]])
    o_new, s_new = relocation_params(torch.tensor([o]), scales, torch.tensor([n]))
    assert 1 - (1 - float(o_new)) ** n == pytest.approx(o, rel=1e-5)  # n copies composite to the old opacity
    D = _exact_D(Fraction(float(o_new)), n)
    torch.testing.assert_close(s_new, scales * (o / D), rtol=1e-4, atol=0)  # float64 inside: no cancellation
    if n == 1:
        torch.testing.assert_close(s_new, scales)  # one copy: unchanged


def test_relocation_preserves_rendered_opacity():
    """A live Gaussian (o = 0.6) and three dead ones: relocation stacks 4 copies with o_new each, and the
    rendered opacity at its centre stays 1 - (1 - o_new)^4 = 0.6."""
    renderer = get_renderer("torch")
    T = np.eye(4)
    gmap = _map([0.6, 0.001, 0.001, 0.001], spread=0.0)
    with torch.no_grad():
        gmap.params["means"][1:] += torch.tensor([5.0, 0.0, 0.0])  # dead ones elsewhere (off screen)
    centre = (16, 16)
    with torch.no_grad():
        before = renderer.render(*gmap.render_args(), CAM, T).alpha[centre].item()
    moved = relocate(gmap, gmap.opacities.detach() <= 0.005, torch.Generator().manual_seed(0))
    assert moved == 3
    o_new = gmap.opacities.detach()
    torch.testing.assert_close(o_new, torch.full((4,), o_new[0].item()))
    assert 1 - (1 - o_new[0].item()) ** 4 == pytest.approx(0.6, rel=1e-5)
    torch.testing.assert_close(gmap.means.detach(), torch.tensor([[0.0, 0.0, 2.0]]).repeat(4, 1))
    with torch.no_grad():
        after = renderer.render(*gmap.render_args(), CAM, T).alpha[centre].item()
    assert before == pytest.approx(0.6, abs=1e-4)
    assert after == pytest.approx(before, abs=1e-4)


def test_relocation_and_densification_keep_optimizer_state_aligned():
    gen = torch.Generator().manual_seed(0)
    gmap = _map([0.9, 0.001, 0.5, 0.002, 0.7, 0.3], spread=0.3)
    _adam_steps(gmap)
    dead = gmap.opacities.detach() <= 0.005
    relocate(gmap, dead, gen)
    gmap.check_aligned()
    assert torch.all(gmap.adam.exp_avg["means"][dead] == 0)  # relocated slots start with fresh moments
    assert torch.all(gmap.adam.exp_avg_sq["sh0"][dead] == 0)
    # the relocated Gaussians are exact copies of live ones (all parameters, higher SH bands too)
    for i in torch.nonzero(dead).squeeze(1).tolist():
        same = (gmap.params["shN"].detach() == gmap.params["shN"].detach()[i]).all(-1).all(-1)
        assert int(same.sum()) >= 2
    n0 = len(gmap)
    added = sample_add(gmap, 4, cap=100, generator=gen)
    assert added == 4 and len(gmap) == n0 + 4
    gmap.check_aligned()
    assert torch.all(gmap.adam.exp_avg["means"][n0:] == 0)  # appended copies start with fresh moments
    _adam_steps(gmap)  # the optimizer still steps over the resized parameters
    gmap.check_aligned()


def test_densification_never_exceeds_the_cap():
    gen = torch.Generator().manual_seed(0)
    gmap = _map([0.5] * 10, spread=0.2)
    assert sample_add(gmap, 100, cap=13, generator=gen) == 3 and len(gmap) == 13
    assert sample_add(gmap, 5, cap=13, generator=gen) == 0 and len(gmap) == 13
    refiner = MCMCRefiner(MCMCConfig(refine_start=1, refine_every=1, growth_rate=0.5), seed=0)
    for _ in range(10):
        refiner.post_step(gmap, cap=20)
        assert len(gmap) <= 20
    assert len(gmap) == 20
    gmap.check_aligned()


def test_noise_moves_only_transparent_gaussians():
    gmap = _map([0.9, 0.6, 0.001], spread=0.3)
    before = gmap.means.detach().clone()
    inject_noise(gmap, 5e-4 * 5e5, torch.Generator().manual_seed(0))
    shift = (gmap.means.detach() - before).norm(dim=1)
    assert shift[0] < 1e-8 and shift[1] < 1e-8 and shift[2] > 1e-4


def test_regulariser_is_differentiable():
    gmap = _map([0.5, 0.5])
    reg = MCMCRefiner().regulariser(gmap)
    reg.backward()
    assert gmap.params["opacities"].grad.abs().sum() > 0 and gmap.params["scales"].grad.abs().sum() > 0


# ---- random numbers on the map's device -----------------------------------------------------------------------------

def test_cpu_draws_are_those_of_before():
    """On the CPU the generator and its draws are unchanged (the CPU-generator version's):
    the noise is randn(N, 3) from the refiner's generator, the sampling multinomial over the same weights."""
    gmap = _map([0.9, 0.6, 0.001, 0.3], spread=0.3)
    before = gmap.means.detach().clone()
    inject_noise(gmap, 1.0, torch.Generator().manual_seed(5))
    z = torch.randn(4, 3, generator=torch.Generator().manual_seed(5))
    from eligsir_o3d.render.projection import quat_to_rotmat
    o = gmap.opacities.detach()
    M = quat_to_rotmat(gmap.quats.detach()) * gmap.scales.detach()[:, None, :]
    want = torch.einsum("nij,nj->ni", M @ M.transpose(1, 2), z) * torch.sigmoid(100.0 * ((1.0 - o) - 0.995))[:, None]
    # the same draws; on the CPU the arithmetic runs in one compiled pass (_update_kernels): float32 rounding apart
    torch.testing.assert_close(gmap.means.detach(), before + want, atol=1e-7, rtol=1e-6)
    from eligsir_o3d.scheduling.mcmc import _sample
    w = torch.tensor([0.5, 0.0, float("nan"), 2.0])
    got = _sample(w, 50, torch.Generator().manual_seed(1))
    ref = torch.multinomial(torch.tensor([0.5, 0.0, 0.0, 2.0], dtype=torch.float64), 50, replacement=True,
                            generator=torch.Generator().manual_seed(1))
    assert torch.equal(got, ref) and got.device == w.device
    all_dead = _sample(torch.zeros(3), 300, torch.Generator().manual_seed(1))  # uniform, decided without a sync
    assert set(all_dead.tolist()) == {0, 1, 2}


def test_refiner_generator_follows_the_map_and_is_checkpointed():
    refiner = MCMCRefiner(MCMCConfig(refine_start=1, refine_every=2), seed=3)
    gmap = _map([0.9, 0.001, 0.5, 0.002, 0.7, 0.3], spread=0.3)
    for _ in range(3):
        refiner.post_step(gmap, cap=12)
    assert refiner.rng.device == gmap.device
    state = refiner.state_dict()
    assert state["rng_device"] == "cpu"
    twin, twin_map = MCMCRefiner(MCMCConfig(refine_start=1, refine_every=2), seed=3), GaussianMap(1)
    twin.load_state_dict(state)
    twin_map.load_state_dict(copy.deepcopy(gmap.state_dict()))  # on the CPU state_dict() shares storage
    for _ in range(3):
        refiner.post_step(gmap, cap=12)
        twin.post_step(twin_map, cap=12)
    torch.testing.assert_close(twin_map.means.detach(), gmap.means.detach(), atol=0, rtol=0)
    # a state saved on a GPU is kept for that device type and not forced onto the CPU (which reseeds)
    cuda_state = {"rng": torch.zeros(16, dtype=torch.uint8), "rng_device": "cuda:0", "steps": 7, "counts": {}}
    moved = MCMCRefiner(seed=3)
    moved.load_state_dict(cuda_state)
    assert moved.steps == 7 and moved.generator(torch.device("cpu")).device.type == "cpu"
    assert torch.equal(moved.rng.get_state(), torch.Generator().manual_seed(3).get_state())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.cuda
def test_cuda_noise_step_makes_no_host_round_trip():
    """On CUDA the per-update noise is drawn on the device and the step synchronises nothing (sync debug mode
    raises on any device-to-host copy or wait); relocation rounds draw on the device too."""
    gmap = _map([0.9, 0.6, 0.001, 0.3] * 50, spread=0.3)
    cuda = GaussianMap(1, "cuda")
    cuda.add(gmap.means.detach().cuda(), torch.rand(200, 3, device="cuda"), torch.full((200,), 0.05, device="cuda"),
             gmap.opacities.detach().cuda())
    refiner = MCMCRefiner(MCMCConfig(refine_start=1000), seed=0)
    refiner.post_step(cuda, cap=400)  # first step: the generator moves to the device
    assert refiner.rng.device.type == "cuda"
    before = cuda.means.detach().clone()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        refiner.post_step(cuda, cap=400)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert float((cuda.means.detach() - before).abs().max()) > 0
    refiner.cfg.refine_start, refiner.cfg.refine_every = 1, 1
    refiner.post_step(cuda, cap=400)
    cuda.check_aligned()
    assert len(cuda) > 200 and refiner.state_dict()["rng_device"].startswith("cuda")
