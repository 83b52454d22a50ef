"""Reconstructor behaviour on a tiny hand-made scene: both Open3D RGBD flavours, learning, determinism, clean errors."""

import time

import numpy as np
import open3d as o3d
import pytest
import torch

import eligsir_o3d as eo3d

W, H = 48, 36


def _intrinsic():
    return o3d.camera.PinholeCameraIntrinsic(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2)


def _images(shift=0):
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    color = ((((u + shift) // 6 + v // 6) % 2)[..., None] * np.array([180, 40, 60]) + 50).astype(np.uint8)
    depth = np.full((H, W), 1500, np.uint16)
    return color, depth


def _tensor_rgbd(shift=0):
    c, d = _images(shift)
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(c), o3d.t.geometry.Image(d))


def _legacy_rgbd(shift=0):
    c, d = _images(shift)
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(c), o3d.geometry.Image(d), depth_scale=1000.0, depth_trunc=10.0,
        convert_rgb_to_intensity=False)


def _rec(seed=0, **kw):
    # the plain policies: every frame kept, native resolution, new-space seeding (exact, easy-to-count behaviour)
    cfg = eo3d.Config(renderer="torch", seed=seed, ablate=("views", "fidelity", "growth"), **kw)
    cfg.keyframes.every = 1
    cfg.seeding.pixel_stride = 3
    cfg.clock.updates_per_frame = 6
    return eo3d.Reconstructor(_intrinsic(), "cpu", cfg)


def _psnr(rec, color):
    out = rec.render(np.eye(4))
    return -10 * np.log10(((out.color.numpy() - color / 255.0) ** 2).mean())


def test_integrate_tensor_and_legacy_rgbd_and_learn():
    rec = _rec()
    info = rec.integrate(_tensor_rgbd(), np.eye(4))
    assert info["admitted"] and info["added"] > 0 and info["updates"] == 6
    before = _psnr(rec, _images()[0])
    for _ in range(4):
        rec.integrate(_legacy_rgbd(), np.eye(4))
    after = _psnr(rec, _images()[0])
    assert after > before + 1.0, (before, after)
    out = rec.render(np.eye(4))
    assert out.color.shape == (H, W, 3) and out.depth.shape == (H, W) and out.alpha.shape == (H, W)
    covered = out.alpha > 0.5
    assert covered.float().mean() > 0.8
    assert torch.allclose(out.depth[covered], torch.full_like(out.depth[covered], 1.5), atol=0.1)
    assert rec.stats.updates == 30 and rec.stats.supervised_pixels == 30 * W * H


def test_same_seed_same_map():
    maps = []
    for _ in range(2):
        rec = _rec(seed=3)
        for k in range(3):
            rec.integrate(_tensor_rgbd(k), np.eye(4))
        maps.append({n: p.detach().clone() for n, p in rec.gmap.params.items()})
    for n in maps[0]:
        torch.testing.assert_close(maps[0][n], maps[1][n], rtol=0, atol=0)


@pytest.mark.parametrize("pose, message", [
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "non-rigid"),
    (np.eye(3), "4x4"),
])
def test_bad_pose_is_rejected_and_map_unchanged(pose, message):
    rec = _rec()
    rec.integrate(_tensor_rgbd(), np.eye(4))
    before = {n: p.detach().clone() for n, p in rec.gmap.params.items()}
    stats = (rec.stats.frames_released, rec.stats.updates)
    with pytest.raises(eo3d.FrameError, match=message):
        rec.integrate(_tensor_rgbd(), pose)
    assert (rec.stats.frames_released, rec.stats.updates) == stats
    for n, p in rec.gmap.params.items():
        assert torch.equal(p.detach(), before[n])


def test_missing_pose_without_source_names_the_frame():
    rec = _rec()
    with pytest.raises(eo3d.FrameError, match="frame 0: no pose given"):
        rec.integrate(_tensor_rgbd(), None)


def test_save_and_load_ply_renders_the_same(tmp_path):
    rec = _rec()
    rec.integrate(_tensor_rgbd(), np.eye(4))
    a = rec.render(np.eye(4)).color
    rec.save_ply(tmp_path / "m.ply")
    rec2 = _rec()
    rec2.load_ply(tmp_path / "m.ply")
    torch.testing.assert_close(rec2.render(np.eye(4)).color, a)


@pytest.mark.parametrize("renderer", ["torch", "cpu"])
def test_warmup_leaves_the_map_and_the_budget_untouched(renderer):
    cfg = eo3d.Config(renderer=renderer)
    rec = eo3d.Reconstructor(_intrinsic(), "cpu", cfg)
    t0 = time.perf_counter()
    seconds = rec.warmup()
    assert 0.0 < seconds <= time.perf_counter() - t0  # it reports the time it took
    assert len(rec.gmap) == 0 and rec.stats.updates == 0 and rec.stats.mapping_s == 0.0
    assert all(p.grad is None for p in rec.gmap.params.values())
    rec.integrate(_tensor_rgbd(), np.eye(4))
    assert len(rec.gmap) > 0
