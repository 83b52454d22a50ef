"""The pose pre-filter's spacing follows the budget (scheduling.spacing): the configured thresholds wherever one
source frame buys no more than ``views.spacing_updates`` updates (every real-time run on the shipped cost model),
closer views by sqrt(reference / u) beyond it, and the same candidate is filtered or not accordingly."""

import math

import pytest

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.budget.cost import CostModel
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.scheduling import MapGuidedViews
from eligsir_o3d.scheduling.spacing import ViewSpacing
from eligsir_o3d.scheduling.views import ViewConfig
from tests.scheduling.test_scheduling import CAM, _ctx, _plane_frame, _pose

QUARTER_VGA = 160 * 120  # a 640x480 stream's update at the fidelity floor (1/4)
VGA = Camera(640, 480, 525.0, 525.0, 319.5, 239.5)


@pytest.mark.parametrize("gaussians", [0, 4_000, 20_000, 200_000])
def test_real_time_on_the_shipped_model_keeps_the_configured_spacing(gaussians):
    s = ViewSpacing(ViewConfig().spacing_updates)
    s.attach(1.0 / 30.0, None)  # None: the shipped fit, as under real-time replay
    assert s.updates_per_frame(QUARTER_VGA, gaussians) < ViewConfig().spacing_updates
    assert s.factor(QUARTER_VGA, gaussians) == 1.0


def test_a_larger_budget_spaces_views_closer_by_the_square_root():
    cost = CostModel()
    s = ViewSpacing(8.0)
    s.attach(10.0 / 30.0, cost)  # --speed 0.1
    u = (10.0 / 30.0 - cost.frame(4000)) / cost.update(QUARTER_VGA, 4000)
    assert s.updates_per_frame(QUARTER_VGA, 4000) == pytest.approx(u)
    f = s.factor(QUARTER_VGA, 4000)
    assert f == pytest.approx(math.sqrt(8.0 / u)) and 0.3 < f < 0.6  # about 2 cm / 2 deg of 5 cm / 5 deg
    assert s.factor(QUARTER_VGA, 40_000) > f  # a dearer update buys fewer: views stay further apart
    s.attach(100.0 / 30.0, cost)
    assert s.factor(QUARTER_VGA, 4000) < f  # --speed 0.01: closer still
    assert s.counters() == {"spacing": round(s.last, 4), "spacing_min": round(s.smallest, 4)}


def test_disabled_spacing_and_bad_settings():
    off = ViewSpacing(0.0)
    off.attach(100.0, CostModel())
    assert not off.enabled and off.factor(QUARTER_VGA, 0) == 1.0
    assert not ViewSpacing(8.0).enabled  # no budget attached yet: the configured thresholds
    with pytest.raises(ValueError, match="views.spacing_updates"):
        ViewSpacing(-1.0)


def test_the_pose_filter_admits_a_closer_view_when_the_budget_allows():
    near = _pose(0.03, 0, 0, yaw_deg=3.0)  # 3 cm, 3 degrees from the first view: inside 5 cm / 5 deg
    for period, filtered in ((1.0 / 30.0, True), (20.0 / 30.0, False)):
        views, ctx = MapGuidedViews(ViewConfig(min_novelty=0.0)), _ctx()
        views.attach(period, CostModel())
        assert views.admit(_plane_frame(_pose(), 0, cam=VGA), ctx)
        assert views.admit(_plane_frame(near, 1, cam=VGA), ctx) is not filtered
        assert views.counts["pose_filtered"] == int(filtered)
        assert (views.counters()["spacing"] < 1.0) is not filtered


def test_the_reconstructor_hands_its_budget_to_the_view_policy():
    cfg = Config(renderer="torch")
    rec = Reconstructor(CAM, "cpu", cfg)
    assert rec.views.spacing.period_s == pytest.approx(cfg.clock.frame_period_s)
    rec.set_load(0, 10.0 * cfg.clock.frame_period_s, CostModel())
    assert rec.views.spacing.period_s == pytest.approx(10.0 * cfg.clock.frame_period_s)
    f = rec.views.spacing.factor(QUARTER_VGA, 0)
    assert f < 1.0
    fresh = Reconstructor(CAM, "cpu", cfg)
    fresh.views.load_state_dict(rec.views.state_dict())  # a checkpoint keeps what metrics.json reports
    assert fresh.views.counters()["spacing_min"] == rec.views.counters()["spacing_min"] == round(f, 4)
