"""Scales that follow the camera's resolution (scheduling/resolution.py): on a camera larger than 640x480 the
support render, the fidelity controller's idle floor and the budget cap's pricing do the work they do on a 640x480
stream, so a 1280x960 stream's frames and idle updates cost no more than a 640x480 stream's; smaller cameras keep
the set scales."""

import pytest

import eligsir_o3d as eo3d
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.scheduling.fidelity import FidelityConfig, LoadAdaptiveFidelity
from eligsir_o3d.scheduling.growth import GrowthConfig, TargetedGrowth
from eligsir_o3d.scheduling.resolution import camera_factor
from eligsir_o3d.scheduling.support import SupportConfig


def _cam(w, h):
    return Camera(w, h, 0.9 * w, 0.9 * w, w / 2 - 0.5, h / 2 - 0.5)


@pytest.mark.parametrize("size, probe, floor, budget_px", [
    ((640, 480), 0.25, 0.25, 19200),  # the stream the defaults were measured on: nothing changes
    ((848, 480), 0.25, 0.25, 25440),
    ((1280, 960), 0.125, 0.125, 19200),  # coarser render, floor and pricing
    ((1280, 720), 0.125, 0.125, 14400),
    ((2560, 1920), 0.0625, 0.125, 19200),  # the floor stops at the controller's coarsest scale
    ((320, 240), 0.25, 0.25, 4800),  # smaller cameras keep the set scales
    ((160, 120), 0.25, 0.25, 1200),
])
def test_each_scale_follows_the_cameras_pixels(size, probe, floor, budget_px):
    cam = _cam(*size)
    assert SupportConfig().scale_for(cam) == probe
    f = LoadAdaptiveFidelity(camera=cam)
    assert f.scales[f.floor_level] == floor
    assert TargetedGrowth()._budget_pixels(cam) == budget_px


def test_switched_off_the_set_scales_hold_and_set_scales_follow_the_camera_too():
    big, vga = _cam(1280, 960), _cam(640, 480)
    assert SupportConfig(follow_camera=False).scale_for(big) == 0.25
    f = LoadAdaptiveFidelity(FidelityConfig(floor_follows_camera=False), camera=big)
    assert f.scales[f.floor_level] == 0.25
    assert TargetedGrowth(GrowthConfig(budget_follows_camera=False))._budget_pixels(big) == 320 * 240
    assert LoadAdaptiveFidelity().scales[LoadAdaptiveFidelity().floor_level] == 0.25  # no camera: the scale
    # a set scale means the same image size: 1/2 of 640x480 is 1/4 of 1280x960; a small camera keeps it
    assert SupportConfig(scale=0.5).scale_for(vga) == 0.5 and SupportConfig(scale=0.5).scale_for(big) == 0.25
    assert SupportConfig(scale=1.0).scale_for(_cam(64, 48)) == 1.0
    f = LoadAdaptiveFidelity(FidelityConfig(idle_floor_scale=0.5), camera=vga)
    assert f.scales[f.floor_level] == 0.5
    assert [camera_factor(_cam(w, h)) for w, h in ((640, 480), (848, 480), (320, 240), (1280, 720), (1920, 1440))] \
        == [1.0, 1.0, 2.0, 0.5, 0.25]


def test_a_larger_camera_renders_and_seeds_as_a_640x480_one():
    """The first frame of the rendered room at 1280x960 and at 640x480: the same 160x120 support render and about
    as many seeds from the same view (with the set 1/4 the larger camera's render is 320x240 and seeds four times
    as many)."""
    from eligsir_o3d.datasets import open_sequence

    seeded = {}
    for w, h, follow in ((640, 480, True), (1280, 960, True), (1280, 960, False)):
        seq = open_sequence("synthetic", n_frames=1, width=w, height=h)
        cfg = eo3d.Config(renderer="cpu")
        cfg.support.follow_camera = follow
        cfg.growth.max_seeds_per_frame = 10_000  # no bound below the grid's count
        rec = eo3d.Reconstructor(seq.camera, "cpu", cfg)
        rec.integrate(seq.frame(0), updates=0)
        seeded[(w, follow)] = rec.growth.counts["seeded"]
        probe = rec.views.probe.check(seq.frame(0), rec.context()).camera
        assert probe.pixels == (160 * 120 if follow else 320 * 240)
    assert seeded[(1280, True)] == pytest.approx(seeded[(640, True)], rel=0.15), seeded
    assert seeded[(1280, False)] > 3 * seeded[(640, True)], seeded
