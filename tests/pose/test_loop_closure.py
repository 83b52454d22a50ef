"""Loop closure (pose.loops, pose.pose_graph, pose.loop_closure) and the map that follows it (core.anchors).

The synthetic room's one loop (48 frames at 160x120, each one a keyframe), walked once and then 2 frames more
along its start, is tracked by a fake tracker whose error grows along the path (tests/helpers/loop_room.py); loop
closure must bring the last frame back to its true pose (1 cm / 0.5 deg). A wrong loop edge injected on purpose
must be pruned by the graph's line process and leave the result as good. Verification in the worker process:
tests/pose/test_loop_worker.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eligsir_o3d.core.anchors import move_anchored
from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.pose.loop_closure import LoopClosure, LoopClosureConfig, loop_closure_for
from eligsir_o3d.pose.loops import LoopConfig
from eligsir_o3d.scheduling.mcmc import relocate, sample_add
from helpers.loop_room import LOOP, N, DriftingSource, drifted, make_room
from helpers.loop_room import loop_config as _config
from helpers.loop_room import pose_error as _err
from helpers.loop_room import rot as _rot


@pytest.fixture(scope="module")
def room():
    return make_room()


def _run(room, lc):
    seq, depths, poses = room
    raw = drifted(poses)
    final = [lc.on_frame(i, raw[i], depths[i], seq.camera) for i in range(N)]
    return raw, final


def test_synthetic_loop_closes(room):
    poses = room[2]
    lc = LoopClosure(_config())
    raw, _ = _run(room, lc)
    before = _err(poses[-1], raw[-1])
    after = _err(poses[-1], lc.pose_of(N - 1, raw[-1]))
    assert before[0] > 0.03 and before[1] > 1.0, before  # the drift is real
    assert after[0] < 0.01 and after[1] < 0.5, (before, after)
    c = lc.counters()
    assert c["loops_accepted"] >= 1 and c["optimisations"] >= 1, c


def test_wrong_loop_edge_is_pruned(room):
    poses = room[2]
    lc = LoopClosure(_config())
    wrong = _rot(np.array([0.0, 0.0, 1.0]), 8.0)
    wrong[:3, 3] = [0.3, -0.2, 0.1]
    lc.injected.append((LOOP, wrong))  # replaces the first accepted loop edge from that frame on
    raw, _ = _run(room, lc)
    assert not lc.injected, "no loop edge was replaced"
    c = lc.counters()
    assert c["rejected_by_graph"] >= 1, c
    after = _err(poses[-1], lc.pose_of(N - 1, raw[-1]))
    assert after[0] < 0.01 and after[1] < 0.5, after


def test_state_round_trip(room):
    seq, depths, poses = room
    lc = LoopClosure(_config())
    raw = drifted(poses)
    for i in range(LOOP):
        lc.on_frame(i, raw[i], depths[i], seq.camera)
    other = LoopClosure(_config())
    other.load_state_dict(lc.state_dict())
    for i in range(LOOP, N):
        a, b = lc.on_frame(i, raw[i], depths[i], seq.camera), other.on_frame(i, raw[i], depths[i], seq.camera)
        np.testing.assert_allclose(a, b, atol=1e-9)
    timing = ("seconds", "keyframe_seconds", "wait_seconds")
    assert {k: v for k, v in lc.counters().items() if k not in timing} == {
        k: v for k, v in other.counters().items() if k not in timing}


def test_a_state_without_odometry_edges_takes_the_trackers(room):
    """A checkpoint written before edges could be refined has no ``odo_rel``: the tracker's relative poses."""
    seq, depths, poses = room
    lc = LoopClosure(_config())
    raw = drifted(poses)
    for i in range(10):
        lc.on_frame(i, raw[i], depths[i], seq.camera)
    state = lc.state_dict()
    del state["odo_rel"]
    other = LoopClosure(_config())
    other.load_state_dict(state)
    assert len(other.odo_rel) == len(lc.odo_rel)
    for a, b in zip(other.odo_rel, lc.odo_rel):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_background_follows_the_clock_unless_set():
    cfg = LoopClosureConfig()
    assert not loop_closure_for(cfg, tracked=True).background  # a deterministic replay verifies inline
    assert loop_closure_for(cfg, tracked=True, realtime=True).background
    assert not loop_closure_for(LoopClosureConfig(background="off"), tracked=True, realtime=True).background
    assert loop_closure_for(LoopClosureConfig(background="on"), tracked=True).background
    with pytest.raises(ValueError, match="loops.background"):
        loop_closure_for(LoopClosureConfig(background="maybe"), tracked=True)


def test_the_live_path_is_drawn_at_the_loop_closed_poses():
    """The live view's path (visual.live.LiveView.path_centres) takes each frame's pose now, so a loop closure
    moves the drawn path at the next push."""
    from types import SimpleNamespace

    from eligsir_o3d.visual.live import LiveView

    view = LiveView.__new__(LiveView)  # no server: only the path
    view._path = [(i, np.eye(4)) for i in range(3)]
    shifted = lambda i, T: T @ np.array([[1, 0, 0, 0.1 * i], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    assert np.allclose(view.path_centres(SimpleNamespace(loops=None))[:, 0], 0.0)
    assert np.allclose(view.path_centres(SimpleNamespace(loops=SimpleNamespace(pose_of=shifted)))[:, 0], [0, 0.1, 0.2])


def test_on_only_for_trackers():
    cfg = LoopClosureConfig()
    assert loop_closure_for(cfg, tracked=False) is None
    assert isinstance(loop_closure_for(cfg, tracked=True), LoopClosure)
    assert loop_closure_for(LoopClosureConfig(enabled="off"), tracked=True) is None
    assert isinstance(loop_closure_for(LoopClosureConfig(enabled="on"), tracked=False), LoopClosure)
    with pytest.raises(ValueError, match="auto, on or off"):
        loop_closure_for(LoopClosureConfig(enabled="maybe"), tracked=True)


def test_refined_odometry_edges_remove_the_trackers_drift_without_a_loop(room):
    """Keyframe-to-keyframe registration replaces the drifting tracker's relative poses (no loop closed here:
    candidates are out of reach), so the corrected end pose is nearer the truth than the tracker's."""
    import dataclasses

    poses = room[2]
    lc = LoopClosure(dataclasses.replace(_config(), min_gap=10**6, refine_edges="on"))
    raw, final = _run(room, lc)
    before, after = _err(poses[-1], raw[-1]), _err(poses[-1], final[-1])
    c = lc.counters()
    assert c["refined_edges"] >= N // 2 and c["loops_found"] == 0, c
    assert after[0] < 0.6 * before[0] and after[1] < 0.6 * before[1], (before, after)


def test_a_refined_edge_may_correct_the_tracker_as_far_as_a_loop_may(room):
    """A tracker edge 20 cm off (a jump): the registration finds the true relative pose and replaces it, since the
    refinement's bound is the loop test's (``max_shift``); a tighter bound keeps exactly this worst edge."""
    import dataclasses

    from eligsir_o3d.core.camera import invert_pose
    from eligsir_o3d.pose.loops import Keyframe, keyframe_cloud, odometry_edge

    seq, depths, poses = room
    cfg = dataclasses.replace(_config(), refine_edges="on")
    assert (cfg.refine_max_shift, cfg.refine_max_turn_deg) == (cfg.max_shift, cfg.max_turn_deg)
    jump = np.eye(4)
    jump[0, 3] = 0.2
    truth = invert_pose(poses[10]) @ poses[12]
    keys = [Keyframe(10, poses[10], keyframe_cloud(depths[10], seq.camera, cfg)),
            Keyframe(12, poses[10] @ truth @ jump, keyframe_cloud(depths[12], seq.camera, cfg))]
    T, _, refined = odometry_edge(keys, 1, cfg, True)
    assert refined and _err(truth, T)[0] < 0.01, _err(truth, T)
    T, _, refined = odometry_edge(keys, 1, dataclasses.replace(cfg, refine_max_shift=0.15), True)
    assert not refined and abs(_err(truth, T)[0] - 0.2) < 1e-9


def _jumping(poses, at: int, jump: np.ndarray) -> list[np.ndarray]:
    """A tracker with the true relative motions except one, ``at - 1 -> at``, off by ``jump``."""
    from eligsir_o3d.core.camera import invert_pose

    out = [poses[0].copy()]
    for k in range(1, len(poses)):
        rel = invert_pose(poses[k - 1]) @ poses[k]
        out.append(out[-1] @ (rel @ jump if k == at else rel))
    return out


def test_skip_edges_outvote_a_trackers_jump(room):
    """One tracker edge 5 cm off, no loop in reach, edges not refined: each keyframe's registration onto the
    keyframe before its predecessor spans the jump twice, and the graph optimised at the end follows those two
    rather than the one wrong edge."""
    import dataclasses

    seq, depths, poses = room
    jump = np.eye(4)
    jump[0, 3] = 0.05
    raw = _jumping(poses, 20, jump)
    cfg = dataclasses.replace(_config(), min_gap=10**6, refine_edges="off")
    results = {}
    for mode in ("off", "on"):
        lc = LoopClosure(dataclasses.replace(cfg, skip_edges=mode))
        for i in range(N):
            lc.on_frame(i, raw[i], depths[i], seq.camera)
        lc.finish()
        results[mode] = (_err(poses[-1], lc.pose_of(N - 1, raw[-1])), lc.counters())
    (off, c_off), (on, c_on) = results["off"], results["on"]
    assert c_off["skip_edges"] == 0 and c_off["optimisations"] == 0 and abs(off[0] - 0.05) < 0.005, (off, c_off)
    assert c_on["skip_edges"] >= N - 4 and c_on["optimisations"] == 1 and c_on["loops_found"] == 0, c_on
    assert on[0] < 0.4 * off[0], (off, on)


def test_skip_edges_survive_a_checkpoint(room):
    import dataclasses

    seq, depths, poses = room
    cfg = dataclasses.replace(_config(), skip_edges="on")
    lc, raw = LoopClosure(cfg), drifted(poses)
    for i in range(10):
        lc.on_frame(i, raw[i], depths[i], seq.camera)
    other = LoopClosure(cfg)
    other.load_state_dict(lc.state_dict())
    assert len(other.skip_edges) == len(lc.skip_edges) >= 7
    for a, b in zip(other.skip_edges, lc.skip_edges):
        assert (a.source, a.target) == (b.source, b.target) and not a.loop
        np.testing.assert_allclose(a.transform, b.transform, atol=1e-12)
    state = lc.state_dict()
    del state["skip_edges"]  # a checkpoint from before skip edges
    other.load_state_dict(state)
    assert other.skip_edges == []


def test_refined_edges_are_on_for_the_refine_sources_only():
    cfg = LoopClosureConfig()
    assert loop_closure_for(cfg, tracked=True, source="kiss-icp").cfg.refine_edges == "on"
    assert loop_closure_for(cfg, tracked=True, source="odometry").cfg.refine_edges == "off"
    assert loop_closure_for(cfg, tracked=True, source="kiss-icp").cfg.skip_edges == "on"
    assert loop_closure_for(cfg, tracked=True, source="odometry").cfg.skip_edges == "off"
    with pytest.raises(ValueError, match="skip_edges"):
        loop_closure_for(LoopClosureConfig(detect=LoopConfig(skip_edges="maybe")), tracked=True)
    off = LoopClosureConfig(detect=LoopConfig(refine_edges="off"))
    assert loop_closure_for(off, tracked=True, source="kiss-icp").cfg.refine_edges == "off"
    with pytest.raises(ValueError, match="refine_edges"):
        loop_closure_for(LoopClosureConfig(detect=LoopConfig(refine_edges="maybe")), tracked=True)


def test_anchors_follow_every_row_change_and_move_rigidly():
    g = GaussianMap()
    gen = torch.Generator().manual_seed(0)
    for anchor in (3, 7, 9):
        g.anchor_view = anchor
        g.add(torch.randn(50, 3, generator=gen), torch.rand(50, 3, generator=gen), torch.full((50, 3), 0.05), 0.5,
              torch.nn.functional.normalize(torch.randn(50, 4, generator=gen), dim=1))
    # a fingerprint per row that every population change carries with it: the mean's x
    key = {round(float(x), 5): int(a) for x, a in zip(g.means.detach()[:, 0], g.anchors)}
    dead = torch.zeros(len(g), dtype=torch.bool)
    dead[::7] = True
    relocate(g, dead, gen)
    sample_add(g, 20, 1000, gen)
    g.remove(torch.arange(len(g)) % 5 == 0)
    g.check_aligned()
    assert len(g.anchors) == len(g)
    for x, a in zip(g.means.detach()[:, 0], g.anchors):
        assert key[round(float(x), 5)] == int(a)
    g.adam.exp_avg["means"].normal_(generator=gen)
    g.adam.exp_avg["quats"].normal_(generator=gen)
    before = {n: g.params[n].detach().clone() for n in ("means", "quats")}
    m_before = g.adam.exp_avg["means"].clone()
    A, B = np.eye(4), _rot(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 20.0)
    B[:3, 3] = [0.1, -0.2, 0.05]
    moved = move_anchored(g, {7: (A, B)})
    sel = g.anchors == 7
    assert moved == int(sel.sum()) > 0
    R, t = torch.tensor(B[:3, :3], dtype=torch.float32), torch.tensor(B[:3, 3], dtype=torch.float32)
    torch.testing.assert_close(g.means[sel], before["means"][sel] @ R.T + t, atol=1e-5, rtol=0)
    torch.testing.assert_close(g.means[~sel], before["means"][~sel])
    torch.testing.assert_close(g.adam.exp_avg["means"][sel], m_before[sel] @ R.T, atol=1e-5, rtol=0)
    from eligsir_o3d.render.projection import quat_to_rotmat
    Rq = quat_to_rotmat(torch.nn.functional.normalize(g.quats[sel].detach(), dim=1))
    Rq0 = quat_to_rotmat(torch.nn.functional.normalize(before["quats"][sel], dim=1))
    torch.testing.assert_close(Rq, R @ Rq0, atol=1e-5, rtol=0)
    state = g.state_dict()
    h = GaussianMap()
    h.load_state_dict(state)
    assert torch.equal(h.anchors, g.anchors)



def test_reconstructor_map_follows_the_loop(room):
    """A tracked Reconstructor: loop closure on by default, the retained views and the anchored Gaussians move
    with the corrected keyframes, and the loop state survives a checkpoint round trip."""
    from eligsir_o3d import Reconstructor
    from eligsir_o3d.config import Config

    seq, _, poses = room
    cfg = Config()
    cfg.loops.detect = _config()
    cfg.clock.updates_per_frame = 1
    rec = Reconstructor(seq.intrinsic, "cpu", cfg, pose_source=DriftingSource(drifted(poses)),
                        depth_scale=seq.depth_scale)
    assert rec.loops is not None
    moved = []
    for i in range(N):
        item = seq[i % LOOP]
        before = rec.gmap.means.detach().clone()
        rec.integrate(item.rgbd, None, timestamp=i / 30.0)
        if rec.loops.counts["optimisations"] and not moved:
            n = len(before)
            moved.append(float((rec.gmap.means.detach()[:n] - before).norm(dim=1).max()))
    assert rec.loops.counters()["loops_accepted"] >= 1
    assert moved and moved[0] > 0.01, moved  # anchored Gaussians moved with their keyframes
    anchored = set(rec.gmap.anchors.tolist()) - {-1}
    assert anchored <= {k.index for k in rec.loops.keys}
    for view in rec.views.views:  # the retained views took the corrected poses
        np.testing.assert_allclose(view.T_world_cam, rec.loops.pose_of(view.index, None), atol=1e-9)
    state = rec.state_dict()
    other = Reconstructor(seq.intrinsic, "cpu", cfg, pose_source=DriftingSource(drifted(poses)),
                          depth_scale=seq.depth_scale)
    other.load_state_dict(state)
    assert other.loops.counters()["loops_accepted"] == rec.loops.counters()["loops_accepted"]
    assert torch.equal(other.gmap.anchors, rec.gmap.anchors) and other.gmap.anchor_view == rec.gmap.anchor_view
