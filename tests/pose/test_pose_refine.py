"""Per-training-view pose refinement (eligsir_o3d/pose_refine.py): the probe's gradient is the pose gradient, a
view's correction is learned back from its image, and the Reconstructor learns, saves and restores it for
training renders only."""

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest
import torch

import eligsir_o3d as eo3d
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.pose.refine import PoseRefineConfig, PoseRefiner, _rot_exp, _rot_log
from eligsir_o3d.render import get_renderer

W, H = 48, 36


def _textured_wall(n=400, seed=0):
    """Gaussians on a 1.6 x 1.2 m wall at z = 1.5 m with a checker texture (a pose error shows as an image shift)."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([1.6, 1.2])
    means = torch.cat([xy, torch.full((n, 1), 1.5)], 1)
    means[:, 2] += 0.2 * xy[:, 0]  # not a fronto-parallel plane: rotations and translations differ in the image
    checker = ((torch.floor(xy[:, 0] / 0.15) + torch.floor(xy[:, 1] / 0.15)) % 2)[:, None]
    colors = checker * torch.tensor([0.9, 0.2, 0.3]) + 0.05
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1)
    scales = torch.full((n, 3), 0.03)
    opacities = torch.full((n,), 0.9)
    return means, quats, scales, opacities, colors


def _pose(xi: torch.Tensor) -> np.ndarray:
    D = np.eye(4)
    D[:3, :3] = _rot_exp(xi[:3].double().numpy())
    D[:3, 3] = xi[3:].double().numpy()
    return D


def _camera():
    return Camera(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2)


def _qmul(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Differentiable Rodrigues in torch (the oracle's; the package's pose algebra is numpy)."""
    th = torch.sqrt((w * w).sum() + 1e-30)
    z = torch.zeros((), dtype=w.dtype)
    K = torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]), torch.stack([-w[1], w[0], z])])
    return torch.eye(3, dtype=w.dtype) + torch.sin(th) / th * K + (1 - torch.cos(th)) / th ** 2 * (K @ K)


def _moved_map(args, T, delta):
    """The oracle: the map moved exactly (differentiably in ``delta``) so that rendering it at ``T`` is rendering
    the original at ``T exp(delta)``: points by ``T exp(delta)^-1 T^-1``, orientations by the world rotation
    ``R Rd^T R^T`` as a quaternion ``qR (qd^-1) qR^-1``."""
    means, quats, *rest = args
    R, t = torch.as_tensor(T[:3, :3]), torch.as_tensor(T[:3, 3])
    Rd = _so3_exp(delta[:3])
    A = R @ Rd.T @ R.T  # the world rotation of the move, about the camera centre, then the shift -R Rd^T v
    moved = (means - t) @ A.T + t - R @ Rd.T @ delta[3:]
    th = torch.sqrt((delta[:3] ** 2).sum() + 1e-30)
    q_inv = torch.cat([torch.cos(th / 2).reshape(1), -torch.sin(th / 2) / th * delta[:3]])
    w = 0.5 * np.sqrt(max(1.0 + np.trace(T[:3, :3]), 1e-12))  # qR of a pose with trace > -1 (true here)
    qR = torch.tensor([w, (T[2, 1] - T[1, 2]) / (4 * w), (T[0, 2] - T[2, 0]) / (4 * w), (T[1, 0] - T[0, 1]) / (4 * w)],
                      dtype=torch.float64)
    qM = _qmul(_qmul(qR, q_inv), qR * torch.tensor([1.0, -1, -1, -1], dtype=torch.float64))
    return (moved, _qmul(qM.expand_as(quats), quats), *rest)


def test_the_probe_gradient_is_the_gradient_of_the_rendered_pose():
    """The gradient the probe sums from the means' and rotations' gradients equals autograd through an exact move
    of the map by a right perturbation of the pose, on the fast CPU rasteriser and on the reference (colour and
    depth; finite differences are no oracle here, the rasterisers' cut-offs make the loss piecewise)."""
    wall = _textured_wall()
    g = torch.Generator().manual_seed(1)
    quats = torch.randn(len(wall[0]), 4, generator=g)  # general orientations: the rotation term matters
    scales = torch.rand(len(wall[0]), 3, generator=g) * 0.04 + 0.01
    args = tuple(a.double() for a in (wall[0], quats, scales, wall[3], wall[4]))
    cam, bg = _camera(), torch.zeros(3, dtype=torch.float64)
    T = np.linalg.inv(_general_pose([0.1, -0.2, 0.05], [0.2, -0.1, 0.05]))
    frame = SimpleNamespace(index=0, T_world_cam=T)
    for backend in ("cpu", "torch"):
        r = get_renderer(backend, torch.device("cpu"))
        target = r.render(*args, cam, T, bg).color.detach() * 0.8

        def loss(out):
            return ((out.color - target) ** 2).sum() + 0.1 * (out.depth ** 2).sum()

        ref = PoseRefiner(PoseRefineConfig(enabled=True, min_updates=0, reg=0.0))
        ref.state[0] = ref._new_state(frame, torch.tensor([0.01, -0.02, 0.005, 0.01, 0.02, -0.01], dtype=torch.float64))
        probed, Tr = ref.render_args(frame, args)
        np.testing.assert_allclose(Tr, ref.pose(frame))
        assert torch.equal(probed[0], args[0]) and torch.equal(probed[1], args[1])  # the identity forward
        loss(r.render(*probed, cam, Tr, bg)).backward()
        got = ref._live[1].grad
        delta = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        loss(r.render(*_moved_map(args, Tr, delta), cam, Tr, bg)).backward()
        want = delta.grad.numpy()
        assert np.abs(want[:3]).max() > 1.0 and np.abs(want[3:]).max() > 1.0  # the pose matters to this loss
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max(), err_msg=backend)
        leaves = (args[0].clone().requires_grad_(True), args[1].clone().requires_grad_(True), *args[2:])
        probed, _ = ref.render_args(frame, leaves)  # a map that learns too: the same pose gradient, and its own
        loss(r.render(*probed, cam, Tr, bg)).backward()
        np.testing.assert_allclose(ref._live[1].grad, got, rtol=1e-9, atol=1e-9 * np.abs(got).max())
        assert leaves[0].grad is not None and leaves[1].grad is not None
        delta.grad = None  # the oracle's map moved by a small delta renders as the original at T exp(delta)
        e = torch.tensor([0.02, -0.01, 0.03, 0.01, 0.02, -0.02], dtype=torch.float64)
        moved = r.render(*_moved_map(args, Tr, e), cam, Tr, bg).color
        assert (moved - r.render(*args, cam, Tr @ _pose(e), bg).color).abs().max() < 1e-4


def test_a_views_pose_error_is_learned_back_from_its_image():
    r = get_renderer("cpu", torch.device("cpu"))
    args, cam, bg = _textured_wall(), _camera(), torch.zeros(3)
    truth = torch.tensor([0.01, -0.015, 0.005, 0.02, -0.015, 0.0])  # ~1 degree, ~2.5 cm: several pixels here
    target = r.render(*args, cam, _pose(truth), bg).color
    frame = SimpleNamespace(index=7, T_world_cam=np.eye(4))  # the given pose is the identity: wrong by `truth`
    ref = PoseRefiner(PoseRefineConfig(enabled=True, lr=3e-3, reg=0.0, min_updates=0))
    losses = []
    for _ in range(80):
        probed, T = ref.render_args(frame, args)
        loss = (r.render(*probed, cam, T, bg).color - target).abs().mean()
        loss.backward()
        ref.step()
        losses.append(float(loss.detach()))
    err0 = float(truth.norm())
    err1 = float((ref.correction(7).float() - truth).norm())
    assert err1 < 0.3 * err0, (err0, err1, ref.correction(7))
    assert losses[-1] < 0.5 * losses[0]
    np.testing.assert_allclose(ref.pose(frame), _pose(ref.correction(7)), atol=1e-12)


def test_disabled_or_regularised_refiner():
    args = _textured_wall(50)
    frame = SimpleNamespace(index=0, T_world_cam=np.eye(4))
    off = PoseRefiner(PoseRefineConfig(enabled=False))
    assert off.render_args(frame, args) == (args, frame.T_world_cam) and not off.state
    off.step()  # nothing to step: no error
    late = PoseRefiner(PoseRefineConfig(enabled=True, min_updates=2))
    for _ in range(2):  # the view's first 2 renders: the map as it is, at the given pose, nothing learned
        assert late.render_args(frame, args) == (args, frame.T_world_cam) and late._live is None
    probed, _ = late.render_args(frame, args)  # then it is refined
    assert probed[0] is not args[0] and probed[2] is args[2] and late._live is not None
    on = PoseRefiner(PoseRefineConfig(enabled=True, reg=2.0, lr=1e-3, min_updates=0))
    on.state[0] = on._new_state(frame, torch.full((6,), 0.1, dtype=torch.float64))
    _, T = on.render_args(frame, args)
    np.testing.assert_allclose(T, on.pose(frame))  # rendered at the refined pose
    on._live[1].grad = np.zeros(6)  # an image that says nothing: reg * |xi|^2 pulls toward the given pose
    on.step()
    np.testing.assert_allclose(on.correction(0).numpy(), np.full(6, 0.1 - 1e-3), atol=1e-5)


def _images(shift):
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    color = ((((u + shift) // 6 + v // 6) % 2)[..., None] * np.array([180, 40, 60]) + 50).astype(np.uint8)
    depth = (1500 + 8 * u).astype(np.uint16)
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(depth))


def _rec(**pose_refine):
    cfg = eo3d.Config(renderer="cpu", seed=0, ablate=("views", "fidelity", "growth"))
    cfg.keyframes.every = 1
    cfg.seeding.pixel_stride = 4
    cfg.clock.updates_per_frame = 4
    pose_refine.setdefault("enabled", True)  # off by default: these tests are about the refiner
    for k, v in pose_refine.items():
        setattr(cfg.pose_refine, k, v)
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2)
    return eo3d.Reconstructor(intr, "cpu", cfg)


def _feed(rec):
    # the images shift by one pixel per frame while the given poses stay put: poses that are wrong by a pixel
    for k in range(3):
        rec.integrate(_images(k), np.eye(4))


def test_reconstructor_learns_saves_and_restores_training_view_corrections(tmp_path):
    rec = _rec(enabled=True, lr=2e-3, reg=1.0, min_updates=0)
    _feed(rec)
    assert sorted(rec.pose_refine.state) == [0, 1, 2]
    moved = [float(rec.pose_refine.correction(i).norm()) for i in range(3)]
    assert min(moved) > 0.0, moved
    # held-out renders keep the given pose: rec.render does not go through the corrections
    before = rec.render(np.eye(4)).color.clone()
    rec.pose_refine.state[0]["xi"] += 0.05
    assert torch.equal(rec.render(np.eye(4)).color, before)
    rec.pose_refine.state[0]["xi"] -= 0.05
    back = eo3d.Reconstructor.load(rec.save(tmp_path / "ck.pt"))
    for i in range(3):
        assert torch.equal(back.pose_refine.correction(i), rec.pose_refine.correction(i))
        assert back.pose_refine.state[i]["t"] == rec.pose_refine.state[i]["t"]
    a, b = rec.optimize(2), back.optimize(2)
    assert a == b == 2
    assert torch.equal(rec.gmap.means, back.gmap.means)  # the restored refiner continues the same trajectory


def test_zero_learning_rate_is_the_plain_mapper():
    plain, zero = _rec(enabled=False), _rec(enabled=True, lr=0.0, reg=0.0, min_updates=0)
    _feed(plain)
    _feed(zero)
    assert not plain.pose_refine.state
    assert torch.allclose(plain.gmap.means, zero.gmap.means, atol=1e-5)
    assert all(float(zero.pose_refine.correction(i).abs().max()) == 0.0 for i in range(3))


def test_centred_corrections_keep_the_map_on_the_given_trajectory():
    r = get_renderer("cpu", torch.device("cpu"))
    args, cam, bg = _textured_wall(200), _camera(), torch.zeros(3)
    truth = torch.tensor([0.0, 0.0, 0.0, 0.03, 0.0, 0.0])  # every view wrong by the same 3 cm: a common motion
    frames = []
    for k, yaw in enumerate((-0.15, 0.0, 0.15)):
        T = _pose(torch.tensor([0.0, yaw, 0.0, 0.0, 0.0, 0.0]))
        frames.append((SimpleNamespace(index=k, T_world_cam=T), r.render(*args, cam, T @ _pose(truth), bg).color))
    for centred in (False, True):
        ref = PoseRefiner(PoseRefineConfig(enabled=True, lr=3e-3, reg=0.0, min_updates=0, centred=centred))
        for _ in range(8):
            for frame, target in frames:
                probed, T = ref.render_args(frame, args)
                (r.render(*probed, cam, T, bg).color - target).abs().mean().backward()
                ref.step()
        R = [torch.as_tensor(f.T_world_cam[:3, :3]) for f, _ in frames]
        mean_t = sum(R[i] @ ref.correction(i)[3:] for i in range(3)) / 3
        mean_w = sum(R[i] @ ref.correction(i)[:3] for i in range(3)) / 3
        if centred:  # the common part is left to the map: the views' world-frame mean stays at the identity
            assert float(mean_t.norm()) < 1e-9 and float(mean_w.norm()) < 1e-9
        else:  # uncentred, the views move together toward the common error
            assert float(mean_t.norm()) > 5e-3, mean_t


def _refined(indices, xis, poses):
    ref = PoseRefiner(PoseRefineConfig(enabled=True, min_updates=0, heldout_poses="carried"))
    for i, xi, T in zip(indices, xis, poses):
        ref.render_args(SimpleNamespace(index=i, T_world_cam=T), _textured_wall(4))
        ref.state[i]["xi"] = xi.double()
        ref.state[i]["t"] = 1
    return ref


def _general_pose(w, t):
    T = np.eye(4)
    T[:3, :3] = _rot_exp(w)
    T[:3, 3] = t
    return T


def test_a_held_out_pose_is_carried_by_its_neighbours_world_correction():
    """A held-out view between two refined views that share one world-frame pose error gets that error removed."""
    Ta, Tb = _general_pose([0.1, 0.3, -0.05], [0.2, 0.1, 1.0]), _general_pose([0.12, 0.4, -0.02], [0.3, 0.1, 1.1])
    Th = _general_pose([0.11, 0.35, -0.04], [0.25, 0.1, 1.05])  # the held-out camera, between them
    E = _general_pose([0.01, -0.02, 0.005], [0.0, 0.0, 0.0])  # a common drift: rotation about each camera centre
    shift = np.array([0.02, -0.01, 0.015])
    # each refined view's correction xi in its own frame, so that T exp(xi) = [Er R, t + shift]
    xis = []
    for T in (Ta, Tb):
        Rc = T[:3, :3].T @ E[:3, :3] @ T[:3, :3]
        w = torch.as_tensor(_rot_log(Rc))
        xis.append(torch.cat([w, torch.as_tensor(T[:3, :3].T @ shift)]))
    ref = _refined([10, 20], xis, [Ta, Tb])
    for i, T in ((10, Ta), (20, Tb)):  # a refined view's carried pose is its refined pose
        np.testing.assert_allclose(ref.carried_pose(i, T), ref.pose(SimpleNamespace(index=i, T_world_cam=T)),
                                   atol=1e-10)
    got = ref.carried_pose(15, Th)
    np.testing.assert_allclose(got[:3, :3], E[:3, :3] @ Th[:3, :3], atol=1e-9)
    np.testing.assert_allclose(got[:3, 3], Th[:3, 3] + shift, atol=1e-9)
    # before the first refined view, the nearest correction; with carrying off, the given pose
    np.testing.assert_allclose(ref.carried_pose(3, Th)[:3, 3], Th[:3, 3] + shift, atol=1e-9)
    ref.cfg.heldout_poses = "given"
    assert np.array_equal(ref.carried_pose(15, Th), Th) and not ref.carries
    assert np.array_equal(ref.heldout_pose(15, Th), Th)


def test_aligned_held_out_poses_take_the_one_rigid_motion_of_the_training_views():
    """``heldout_poses="aligned"``: when every refined view moved by one rigid motion E of the world, a held-out pose
    is rendered at E times its given pose; per-view scatter around E averages out; unknown rules are refused."""
    poses = [_general_pose([0.1 * k, 0.3 - 0.1 * k, 0.02 * k], [0.2 * k, 0.1, 1.0 - 0.1 * k]) for k in range(4)]
    E = _general_pose([0.01, -0.02, 0.015], [0.03, -0.01, 0.02])
    xis = []
    for T in poses:  # T exp(xi) = E T
        D = np.linalg.inv(T) @ E @ T
        xis.append(torch.as_tensor(np.concatenate([_rot_log(D[:3, :3]), D[:3, 3]])))
    ref = _refined([0, 10, 20, 30], xis, poses)
    ref.cfg.heldout_poses = "aligned"
    np.testing.assert_allclose(ref.alignment(), E, atol=1e-9)
    Th = _general_pose([0.15, 0.2, 0.03], [0.25, 0.1, 0.9])
    np.testing.assert_allclose(ref.heldout_pose(15, Th), E @ Th, atol=1e-9)
    assert np.array_equal(ref.heldout_pose(15, Th, "given"), Th)
    np.testing.assert_allclose(ref.heldout_pose(15, Th, "carried"), ref.carried_pose(15, Th, always=True), atol=1e-12)
    for rule in ("nearest", ""):
        with pytest.raises(ValueError, match="held-out pose rule"):
            ref.heldout_pose(15, Th, rule)
    with pytest.raises(ValueError, match="pose_refine.heldout_poses"):
        PoseRefiner(PoseRefineConfig(heldout_poses="nearest"))
    back = PoseRefiner(PoseRefineConfig(heldout_poses="aligned"))
    back.load_state_dict(ref.state_dict())
    np.testing.assert_allclose(back.alignment(), E, atol=1e-9)


def test_carrying_interpolates_between_neighbours_and_ignores_unmoved_views():
    T = np.eye(4)
    ref = _refined([0, 10], [torch.tensor([0.0, 0, 0, 0.01, 0, 0]), torch.tensor([0.0, 0, 0, 0.03, 0, 0])], [T, T])
    assert ref.carries
    np.testing.assert_allclose(ref.carried_pose(5, T)[:3, 3], [0.02, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ref.carried_pose(8, T)[:3, 3], [0.026, 0, 0], atol=1e-12)
    ref.render_args(SimpleNamespace(index=6, T_world_cam=T), _textured_wall(4))  # seen, never stepped: no say
    np.testing.assert_allclose(ref.carried_pose(5, T)[:3, 3], [0.02, 0, 0], atol=1e-12)
    off = PoseRefiner(PoseRefineConfig(enabled=False))
    assert np.array_equal(off.carried_pose(5, T), T) and not off.carries


def test_growth_sees_the_refined_pose_and_a_warm_start_begins_at_the_predecessors_correction():
    T0, T1 = np.eye(4), _general_pose([0.0, 0.05, 0.0], [0.1, 0.0, 0.0])
    ref = _refined([0], [torch.tensor([0.0, 0.01, 0.0, 0.02, 0.0, 0.0])], [T0])
    f0 = SimpleNamespace(index=0, T_world_cam=T0)
    moved = ref.posed(f0)
    assert moved is not f0 and f0.T_world_cam is T0  # a copy: the stored view keeps its given pose
    np.testing.assert_allclose(moved.T_world_cam, ref.pose(f0), atol=1e-12)
    f1 = SimpleNamespace(index=1, T_world_cam=T1)
    assert ref.posed(f1) is f1  # no correction yet: growth uses the given pose
    ref.warm_start(f1)  # off by default
    assert 1 not in ref.state
    ref.cfg.warm_start = True
    ref.warm_start(f1)
    np.testing.assert_allclose(ref.pose(f1), ref.carried_pose(1, T1, always=True), atol=1e-10)
    assert ref.state[1]["t"] == 0 and 1 not in [k for k, s in ref.state.items() if s["t"] > 0]
    # during its first min_updates the warm-started correction is applied but not learned
    ref.cfg.min_updates = 5
    args = _textured_wall(8)
    got, T = ref.render_args(f1, args)
    assert got is args and ref._live is None
    np.testing.assert_allclose(T, ref.pose(f1), atol=1e-12)


def test_refinement_is_off_by_default_with_the_measured_settings():
    cfg = eo3d.Config().pose_refine
    assert not cfg.enabled and cfg.heldout_poses == "aligned" and not cfg.warm_start
    assert (cfg.lr, cfg.reg, cfg.min_updates) == (1e-3, 1.0, 10)
