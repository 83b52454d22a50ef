"""Adam with a per-Gaussian schedule (eligsir_o3d/row_adam.py, config ``optim.adam``): per-row bias correction,
position step-size decay with a Gaussian's age, warm-up of new Gaussians; counters carried through every change
of the population and through checkpoints."""

import pytest
import torch

from eligsir_o3d.config import Config, apply_override
from eligsir_o3d.core.gaussians import AdamConfig, GaussianMap


def _add(gmap, n, seed):
    g = torch.Generator().manual_seed(seed)
    return gmap.add(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                    0.01 + 0.05 * torch.rand(n, generator=g), 0.05 + 0.9 * torch.rand(n, generator=g),
                    torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))


def _grad_step(gmap, targets, rows=None):
    """One step pulling every parameter row towards ``targets`` (a dict of tensors, rows first)."""
    gmap.zero_grad()
    sel = slice(None) if rows is None else rows
    loss = sum(((gmap.params[n][sel] - t) ** 2).sum() for n, t in targets.items())
    loss.backward()
    gmap.step()


def _targets(n, seed, sh=0):
    g = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=g), "scales": torch.randn(n, 3, generator=g) - 3,
            "quats": torch.randn(n, 4, generator=g), "opacities": torch.randn(n, generator=g),
            "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.randn(n, sh, 3, generator=g)}


@pytest.mark.parametrize("device_fallback", [False, True])
def test_rows_born_together_step_as_torch_adam(monkeypatch, device_fallback):
    """With every Gaussian present from the first step, per-row bias correction is torch's Adam."""
    if device_fallback:  # the torch formula that non-CPU maps use
        monkeypatch.setattr("eligsir_o3d.optim.update_kernels.adam_rows_step",
                            lambda items: pytest.fail("kernel used"), raising=True)
    rows, ref = GaussianMap(1, adam=AdamConfig(row_bias_correction=True)), GaussianMap(1)
    for gm in (rows, ref):
        _add(gm, 40, 0)
    if device_fallback:
        rows.device = torch.device("meta")  # not "cpu": the torch path (tensors stay on the CPU)
    t = _targets(40, 1, sh=3)
    for k in range(6):
        for gm in (rows, ref):
            _grad_step(gm, {n: v * (1 + k) for n, v in t.items()})
    for n in ref.params:
        torch.testing.assert_close(rows.params[n], ref.params[n], rtol=1e-5, atol=1e-6)


def test_late_gaussian_steps_as_if_its_adam_started_at_its_birth():
    """A Gaussian inserted after 1000 updates takes the steps of a fresh Adam; with torch's per-tensor bias
    correction (the default) its first step is ~2.5x larger (first moment 0.1 g over 1 - 0.9^1000, second 0.001
    g^2 over 1 - 0.999^1000)."""
    def late(adam):
        gm = GaussianMap(0, adam=adam)
        _add(gm, 20, 0)
        t = _targets(20, 1)
        for _ in range(1000):
            _grad_step(gm, t)
        idx = _add(gm, 1, 5)
        before = gm.params["means"][idx].detach().clone()
        _grad_step(gm, {n: torch.cat([t[n], _targets(1, 9)[n]]) for n in t})
        return gm.params["means"][idx].detach() - before

    fresh = GaussianMap(0)
    _add(fresh, 1, 5)
    before = fresh.params["means"].detach().clone()
    _grad_step(fresh, _targets(1, 9))
    step_fresh = fresh.params["means"].detach() - before
    torch.testing.assert_close(late(AdamConfig(row_bias_correction=True)), step_fresh, rtol=1e-5, atol=1e-9)
    assert late(AdamConfig()).abs().max() > 2.2 * step_fresh.abs().max()


def test_position_step_decays_with_the_updates_a_gaussian_has_seen():
    """Same gradients, same moments: the position step of a Gaussian that has seen s updates is
    means_decay_to ** min(s / means_decay_updates, 1) times the undecayed one; a Gaussian no gradient reaches does
    not age; the other parameters are not decayed."""
    cfg = AdamConfig(means_decay_to=0.1, means_decay_updates=4)
    dec, ref = GaussianMap(0, adam=cfg), GaussianMap(0, adam=AdamConfig(row_bias_correction=False))
    for gm in (dec, ref):
        _add(gm, 10, 0)
    t = _targets(10, 1)
    seen_rows = torch.arange(10) < 6  # rows 6.. get no gradient
    for k in range(1, 7):
        moves = []
        for gm in (dec, ref):
            before = {n: p.detach().clone() for n, p in gm.params.items()}
            gm.zero_grad()
            # linear: the gradient does not depend on where the decay has put a Gaussian
            loss = sum((gm.params[n][seen_rows] * v[seen_rows]).sum() for n, v in t.items())
            loss.backward()
            gm.step()
            moves.append({n: gm.params[n].detach() - before[n] for n in before})
        factor = 0.1 ** min(k / 4, 1.0)
        torch.testing.assert_close(moves[0]["means"][:6], factor * moves[1]["means"][:6], rtol=1e-4, atol=2e-7)  # float32 positions ~1
        torch.testing.assert_close(moves[0]["sh0"], moves[1]["sh0"], rtol=1e-5, atol=1e-9)
        assert moves[0]["means"][6:].abs().max() == 0
    seen = dec.optimizers["means"].state[dec.params["means"]]["row_seen"]
    assert seen.tolist() == [6.0] * 6 + [0.0] * 4


def test_warmup_ramps_a_new_gaussian_in():
    gm = GaussianMap(0, adam=AdamConfig(warmup_updates=4))
    _add(gm, 3, 0)
    t = _targets(3, 1)
    sizes = []
    for _ in range(6):
        before = gm.params["sh0"].detach().clone()
        _grad_step(gm, t)
        sizes.append(float((gm.params["sh0"].detach() - before).abs().mean()))
    # Adam's normalised steps are ~lr each; the warm-up scales them by 1/4, 2/4, 3/4, 1, 1, 1
    assert sizes[0] < 0.4 * sizes[4] and sizes[1] < 0.7 * sizes[4] and sizes[3] > 0.9 * sizes[4]


def test_row_counters_follow_the_population_and_checkpoints():
    gm = GaussianMap(0, adam=AdamConfig(row_bias_correction=True, means_decay_to=0.5))
    _add(gm, 8, 0)
    for _ in range(3):
        _grad_step(gm, _targets(8, 1))
    _add(gm, 2, 3)
    _grad_step(gm, _targets(10, 2))
    state = lambda g, n="means", k="row_step": g.optimizers[n].state[g.params[n]][k]  # noqa: E731
    assert state(gm).tolist() == [4.0] * 8 + [1.0] * 2
    gm.remove(torch.tensor([True] + [False] * 9))
    gm.check_aligned()
    assert state(gm).tolist() == [4.0] * 7 + [1.0] * 2
    gm.assign(torch.tensor([0]), {"opacities": gm.params["opacities"].detach()[:1].clone()})  # MCMC relocation of one source
    assert state(gm, "opacities")[0] == 0 and state(gm)[0] == 4 and state(gm, k="row_seen")[0] == 4
    gm.check_aligned()
    back = GaussianMap(0, adam=gm.adam)
    back.load_state_dict(gm.state_dict())
    back.check_aligned()
    assert state(back).tolist() == state(gm).tolist() and state(back, k="row_seen").tolist() == [4.0] * 7 + [1.0] * 2


def test_config_reaches_the_map_and_bad_values_are_named():
    from eligsir_o3d.reconstructor import Reconstructor
    from eligsir_o3d.core.camera import Camera

    cfg = Config()
    apply_override(cfg, "optim.adam.row_bias_correction=true")
    apply_override(cfg, "optim.adam.beta2=0.99")
    rec = Reconstructor(Camera(32, 24, 30.0, 30.0, 15.5, 11.5), config=cfg)
    assert rec.gmap.adam.row_bias_correction and rec.gmap.optimizers["means"].param_groups[0]["betas"] == (0.9, 0.99)
    with pytest.raises(ValueError, match="means_decay_to"):
        GaussianMap(0, adam=AdamConfig(means_decay_to=0.0))
    with pytest.raises(ValueError, match="beta2"):
        GaussianMap(0, adam=AdamConfig(beta2=1.0))
