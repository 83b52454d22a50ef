"""The sub-stage timing (budget.stages.detail) names methods by string: each must exist on a default
Reconstructor's parts, so that renaming one fails here instead of silently dropping its timing."""

import eligsir_o3d as eo3d
from eligsir_o3d.budget.stages import DETAIL, StageTimes, detail
from eligsir_o3d.datasets import open_sequence


def test_every_detailed_stage_names_a_method_that_exists():
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    rec = eo3d.Reconstructor(seq.camera, "cpu", eo3d.Config(renderer="cpu"))
    missing = []
    for path, attr, name in DETAIL:
        obj = rec
        for part in filter(None, path.split(".")):
            obj = getattr(obj, part, None)
        if not callable(getattr(obj, attr, None)):
            missing.append(f"{path or 'Reconstructor'}.{attr} ({name})")
    assert not missing, missing


def test_detail_times_the_sub_stages_of_a_run():
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    rec = eo3d.Reconstructor(seq.camera, "cpu", eo3d.Config(renderer="cpu"))
    timing = detail(rec, StageTimes())
    for i in range(len(seq)):
        rec.integrate(seq.frame(i), updates=2)
    assert {"update.select", "update.backward", "update.step", "render", "scheduling.feedback"} <= set(timing.calls)
