"""Area or point supervision (scheduling.supervision): point samples are the source's own pixels under a camera that
projects onto them; the detail coherence tells exact poses from a few pixels of misregistration; the policy decides
once, after its pairs, and keeps its state through a checkpoint."""

from pathlib import Path

import numpy as np
import pytest
import torch

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.core.gaussians import EPS2D
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.scheduling.supervision import SupervisionConfig, SupervisionGrid, detail_coherence


@pytest.fixture(scope="module")
def room():
    return open_sequence("synthetic", n_frames=24, width=160, height=120)


def _project(cam, p):  # camera-frame point -> (u, v), pixel centres at integers
    return cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy


@pytest.mark.parametrize("step,px,py", [(2, 0, 0), (2, 1, 1), (4, 3, 1), (4, 0, 2)])
def test_point_samples_are_source_pixels_where_their_camera_projects(room, step, px, py):
    f = room.frame(3)
    color, depth, cam = f.point_sampled(step, px, py)
    assert (cam.width, cam.height) == (f.camera.width // step, f.camera.height // step)
    assert torch.equal(color, f.color[py::step, px::step][:cam.height, :cam.width])
    assert torch.equal(depth, f.depth[py::step, px::step][:cam.height, :cam.width])
    p = np.array([0.21, -0.13, 1.7])
    u, v = _project(f.camera, p)
    us, vs = _project(cam, p)
    assert us == pytest.approx((u - px) / step) and vs == pytest.approx((v - py) / step)
    i, j = 5, 7  # sample (i, j) is source pixel (px + step i, py + step j): its ray projects onto both centres
    z = 2.0
    q = np.array([(px + step * i - f.camera.cx) * z / f.camera.fx, (py + step * j - f.camera.cy) * z / f.camera.fy, z])
    assert _project(cam, q) == pytest.approx((i, j))


def _turned(T, degrees):
    a = np.deg2rad(degrees)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ R
    return out


def test_detail_coherence_tells_exact_poses_from_a_few_pixels_off(room):
    a, b = room.frame(4), room.frame(8)
    exact = detail_coherence(b, a)
    assert exact is not None and exact > 0.6  # the rendered room's poses and depth are exact
    a.T_world_cam = _turned(a.T_world_cam, 1.0)  # ~2 px at 160x120 (fx 128)
    off = detail_coherence(b, a)
    assert off is not None and off < 0.4 < exact
    assert detail_coherence(b, b) == pytest.approx(1.0, abs=1e-6)  # a view agrees with itself
    far = room.frame(4)
    far.T_world_cam = far.T_world_cam.copy()
    far.T_world_cam[:3, 3] += 50.0  # nothing of one in the other: nothing to measure
    assert detail_coherence(b, far) is None


def test_the_policy_decides_once_after_its_pairs(room):
    grid = SupervisionGrid(SupervisionConfig(pairs=2))
    assert grid.mode == "area" and grid.counters()["decided"] is False
    grid.on_admitted(room.frame(0))
    grid.on_admitted(room.frame(3))
    assert grid.mode == "area" and len(grid.coherence) == 1  # undecided: areas
    grid.on_admitted(room.frame(6))
    assert grid.mode == "point" and grid.counters()["pairs"] == 2 and grid.counters()["coherence_median"] > 0.6
    grid.on_admitted(room.frame(9))
    assert len(grid.coherence) == 2  # decided: nothing more is measured

    rng = torch.Generator().manual_seed(0)
    s = grid.sample(room.frame(9), 0.5, rng, "cpu")
    assert (s.camera.width, s.camera.height) == (80, 60)
    assert s.low_pass == pytest.approx(EPS2D / 4) and s.fitted == room.frame(9).camera
    full = grid.sample(room.frame(9), 1.0, rng, "cpu")  # full resolution: nothing to sample
    assert full.low_pass == EPS2D and full.camera == room.frame(9).camera
    odd = grid.sample(room.frame(9), 0.3, rng, "cpu")  # not a whole step: the area pyramid
    assert odd.low_pass == EPS2D and odd.fitted == odd.camera

    area = SupervisionGrid(SupervisionConfig(mode="area"))
    for i in (0, 3, 6):
        area.on_admitted(room.frame(i))
    assert area.mode == "area" and area.coherence == []
    s = area.sample(room.frame(9), 0.5, rng, "cpu")
    assert s.low_pass == EPS2D and s.fitted == s.camera


def test_point_supervision_seeds_as_finely_as_the_updates_and_reseeds_the_views_before_the_decision(room):
    """A run that decides point samples spaces seeds in pixels of the updates' scale (here a fixed 1/2: 8 source
    pixels instead of 16) and gives the views admitted before the decision the finer grid too; one that decides
    area keeps the probe's grid."""
    runs = {}
    for mode in ("auto", "area"):
        cfg = Config(renderer="cpu", ablate=["fidelity"])
        cfg.fidelity.fixed_scale = 0.5
        cfg.clock.updates_per_frame = 1
        cfg.supervision.mode = mode
        rec = Reconstructor(room.camera, "cpu", cfg)
        for i in range(0, 12, 3):
            rec.integrate(room.frame(i), room.frame(i).T_world_cam)
        runs[mode] = rec
    auto, area = runs["auto"], runs["area"]
    assert auto.supervision.mode == "point" and auto.context().seed_scale == 0.5 and area.context().seed_scale is None
    grown = auto.policy_counters()["growth"]
    assert grown["reseeded"] > 0  # the views before the decision
    assert area.policy_counters()["growth"]["reseeded"] == 0
    assert grown["seeded"] + grown["reseeded"] > 2 * area.policy_counters()["growth"]["seeded"]


def test_a_misregistered_stream_keeps_area_supervision(room):
    grid = SupervisionGrid(SupervisionConfig(pairs=2))
    for k, i in enumerate((0, 2, 4)):
        f = room.frame(i)
        f.T_world_cam = _turned(f.T_world_cam, 1.0 * k)  # each view's pose 1 degree (~2 px) further off than the last
        grid.on_admitted(f)
    assert grid.counters()["decided"] and grid.mode == "area"


def test_the_mode_is_checked_and_survives_a_checkpoint(room, tmp_path):
    with pytest.raises(ValueError, match="supervision.mode"):
        Config(supervision=SupervisionConfig(mode="points")).resolve()
    with pytest.raises(ValueError, match="supervision.pairs"):
        Config(supervision=SupervisionConfig(pairs=0)).resolve()
    cfg = Config(renderer="cpu")
    cfg.clock.updates_per_frame = 2
    rec = Reconstructor(room.camera, "cpu", cfg)
    for i in range(0, 24, 3):
        rec.integrate(room.frame(i), room.frame(i).T_world_cam)
    counters = rec.policy_counters()["supervision"]
    assert counters["decided"] and counters["mode"] == "point"  # the rendered room: exact poses
    assert rec.gmap.low_pass(room.camera) == pytest.approx(EPS2D)  # fitted at the source resolution
    path = tmp_path / "ckpt"
    rec.save(path)
    back = Reconstructor.load(path)
    assert back.policy_counters()["supervision"] == counters

    undecided = Reconstructor(room.camera, "cpu", cfg)
    undecided.integrate(room.frame(0), room.frame(0).T_world_cam)
    undecided.save(tmp_path / "early")
    early = Reconstructor.load(tmp_path / "early")
    assert early.supervision._last is not None and early.supervision._last.index == 0
    early.integrate(room.frame(3), room.frame(3).T_world_cam)
    assert len(early.supervision.coherence) == 1  # measured against the restored view


def test_a_view_too_close_to_the_last_one_is_not_a_pair(room):
    grid = SupervisionGrid(SupervisionConfig(pairs=2))
    first = room.frame(0)
    grid.on_admitted(first)
    near = room.frame(0)
    near.T_world_cam = _turned(first.T_world_cam, 2.0)  # 2 degrees, not moved: closer than 5 cm / 5 degrees
    near.T_world_cam[:3, 3] += 0.01
    grid.on_admitted(near)
    assert grid.coherence == [] and grid._last is first  # still waiting for a view further on
    grid.on_admitted(room.frame(3))
    assert len(grid.coherence) == 1


DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "7scenes_redkitchen_jpg1000").is_dir(),
                                reason="../shared/data is not available")


@needs_data
@pytest.mark.parametrize("name,frames,point", [
    ("replica_office0_micro4", (0, 3, 1), True),  # rendered: its frames agree at full resolution (0.87-0.89)
    ("7scenes_redkitchen_jpg1000", (0, 30, 50), False),  # the first views a real-time run admits (0.56, 0.30)
    ("sun3d_mit76_studyroom_f0935", (0, 8, 13), False),  # (0.18, 0.59)
])
def test_real_recordings_and_a_rendered_one_decide_apart(name, frames, point):
    seq = open_sequence(DATA / name)
    grid = SupervisionGrid(SupervisionConfig(pair_translation_m=0.0, pair_rotation_deg=0.0))
    for i in frames:
        grid.on_admitted(seq.frame(i))
    assert grid.counters()["decided"] and (grid.mode == "point") is point
