"""Sub-stage timing (budget.stages): marked where the work runs (``StageTimes.sub``), timed only with ``detail`` on,
so a default run's ``stage_times`` holds the four stages and a breakdown holds every sub-stage a run reaches."""

import eligsir_o3d as eo3d
from eligsir_o3d.budget.stages import SUB_STAGES, StageTimes
from eligsir_o3d.datasets import open_sequence


def _run(detail: bool):
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    rec = eo3d.Reconstructor(seq.camera, "cpu", eo3d.Config(renderer="cpu"))
    rec.timing.detail = detail
    for i in range(len(seq)):
        rec.integrate(seq.frame(i), updates=2)
    return rec


def test_detail_times_the_sub_stages_of_a_run():
    timing = _run(True).timing
    reached = {"admission.view_bookkeeping", "update.select", "update.backward", "update.step", "update.mcmc",
               "render", "scheduling.select", "scheduling.feedback", "support_render", "growth.voxel_hash",
               "growth.insert", "admission.pose_filter"}
    assert reached <= set(timing.calls), reached - set(timing.calls)
    assert set(timing.calls) - {"admission", "growth", "update"} <= set(SUB_STAGES)  # every name is documented
    assert timing.calls["update.step"] == timing.calls["update"] == 6


def test_without_detail_only_the_stages_are_timed():
    assert set(_run(False).timing.calls) == {"admission", "growth", "update"}


def test_a_sub_stage_without_detail_is_one_shared_no_op():
    t = StageTimes()
    assert t.sub("render") is t.sub("update.step")
    with t.sub("render"):
        pass
    assert t.calls == {}
