"""Coarse-to-fine supervision of the offline reference: stage by stage over a schedule of known length."""

import pytest

from eligsir_o3d import Config
from eligsir_o3d.run.pipeline import RunOptions, run_mapping
from eligsir_o3d.scheduling.coarse_to_fine import CoarseToFine


def _run(policy, n):
    scales = []
    for _ in range(n):
        scales.append(policy.scale())
        policy.observe(0.0, 1, 0)
    return scales


def test_stages_follow_the_progress_and_state_round_trips():
    c = CoarseToFine(10)
    assert _run(c, 12) == [0.25] * 4 + [0.5] * 3 + [1.0] * 5  # past the end it stays at the finest scale
    assert c.counters()["updates_by_scale"] == {"0.25": 4, "0.5": 3, "1": 5}
    d = CoarseToFine(10)
    _run(d, 5)
    e = CoarseToFine(10)
    e.load_state_dict(d.state_dict())
    assert _run(e, 3) == _run(d, 3) == [0.5, 0.5, 1.0]


@pytest.mark.parametrize("stages", [(), ((0.25, 0.5),), ((0.0, 1.0),), ((2.0, 1.0),)])
def test_bad_schedules_are_named(stages):
    with pytest.raises(ValueError, match="coarse-to-fine"):
        CoarseToFine(10, stages)
    with pytest.raises(ValueError, match="total updates"):
        CoarseToFine(0)


def test_offline_reference_runs_coarse_to_fine(tmp_path):
    cfg = Config(renderer="cpu")
    cfg.clock.offline_updates = 10
    opts = RunOptions(max_frames=8, holdout_every=4, eval_every=0, progress=False, plots=False, pictures=False,
                      offline_reference=True)
    m = run_mapping("synthetic", tmp_path, cfg, opts, sequence_options={"n_frames": 8, "width": 64, "height": 48})
    fid = m["policies"]["fidelity"]
    assert fid["policy"] == "coarse_to_fine" and fid["updates_by_scale"] == {"0.25": 4, "0.5": 3, "1": 3}
    assert m["updates"] == 10 and m["map_state"] == "offline-reference"


def test_decayed_lr_is_log_linear():
    from eligsir_o3d.scheduling.coarse_to_fine import decayed_lr

    assert decayed_lr(1e-3, 0.01, 0.0) == pytest.approx(1e-3)
    assert decayed_lr(1e-3, 0.01, 0.5) == pytest.approx(1e-4)
    assert decayed_lr(1e-3, 0.01, 1.0) == pytest.approx(1e-5)
    assert decayed_lr(1e-3, 0.01, 3.0) == pytest.approx(1e-5)  # past the end it stays at the final value


def _offline(tmp_path, **clock):
    cfg = Config(renderer="cpu")
    cfg.clock.offline_updates = 10
    for k, v in clock.items():
        setattr(cfg.clock, k, v)
    seen = []
    opts = RunOptions(max_frames=8, holdout_every=4, eval_every=0, progress=False, plots=False, pictures=False,
                      offline_reference=True)
    from eligsir_o3d.mapper import Reconstructor

    step = Reconstructor._step

    def traced(rec, scale):  # record the means' step size each update is taken with
        seen.append(rec.gmap.adam.lr["means"])
        return step(rec, scale)

    Reconstructor._step = traced
    try:
        m = run_mapping("synthetic", tmp_path, cfg, opts, sequence_options={"n_frames": 8, "width": 64, "height": 48})
    finally:
        Reconstructor._step = step
    return m, seen


def test_offline_means_lr_decays_over_the_schedule(tmp_path):
    m, seen = _offline(tmp_path / "decay", offline_means_lr_final=0.01)
    assert len(seen) == 10 and m["updates"] == 10
    lr0 = seen[0]
    assert seen == pytest.approx([lr0 * 0.01 ** (i / 10) for i in range(10)])
    m, flat = _offline(tmp_path / "flat", offline_means_lr_final=1.0)
    assert flat == [lr0] * 10  # 1: constant, as before
    m, default = _offline(tmp_path / "default")
    assert default == pytest.approx(seen)  # the default decays 100x over the schedule, as 3DGS


def test_offline_stages_come_from_the_config(tmp_path):
    m, _ = _offline(tmp_path, offline_stages=((0.5, 0.5), (1.0, 0.5)))
    assert m["policies"]["fidelity"]["updates_by_scale"] == {"0.5": 5, "1": 5}


def test_bad_offline_lr_decay_is_named():
    from eligsir_o3d.budget import check_clock_config
    from eligsir_o3d.budget.clock import ClockConfig

    with pytest.raises(ValueError, match="offline_means_lr_final"):
        check_clock_config(ClockConfig(offline_means_lr_final=0.0))


def test_offline_policies_come_from_the_factory_and_survive_a_checkpoint(tmp_path):
    """get_policies(cfg, offline=True) builds the offline reference's policies; a checkpoint restores them with no
    setup= hook (offline_frames is part of the state)."""
    import eligsir_o3d as eo3d
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.scheduling import get_policies
    from eligsir_o3d.scheduling.coarse_to_fine import CoarseToFine
    from eligsir_o3d.scheduling.keyframes import StrideKeyframes
    from eligsir_o3d.scheduling.seeding import NewSpaceSeeding

    cfg = Config(renderer="cpu")
    views, fidelity, growth = get_policies(cfg, offline=True, n_source=6)
    assert isinstance(views, StrideKeyframes) and views.cfg.every == 1 and views.cfg.max_views == 6
    assert isinstance(fidelity, CoarseToFine) and fidelity.total == 6 * cfg.clock.offline_updates_per_frame
    assert isinstance(growth, NewSpaceSeeding) and not growth.cfg.dense
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    rec = eo3d.Reconstructor(seq.camera, "cpu", cfg, offline_frames=3)
    for i in range(3):
        rec.integrate(seq.frame(i), updates=2)
    back = eo3d.Reconstructor.load(rec.save(tmp_path / "ck.pt"), sequence=seq)
    assert back.offline_frames == 3 and type(back.fidelity) is CoarseToFine
    assert back.fidelity.updates == rec.fidelity.updates == 6
