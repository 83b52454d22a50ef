"""Coarse-to-fine supervision of the offline reference: stage by stage over a schedule of known length."""

import pytest

from eligsir_o3d import Config
from eligsir_o3d.pipeline import RunOptions, run_mapping
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
