"""Looking at maps: splats read from any 3DGS PLY, held-out pictures, fly-through videos, `eligsir render`, the
pictures of `eligsir map`, and the live view's bookkeeping. The browser test is in test_viewer_browser.py."""

import json
import math
import time

import numpy as np
import pytest
import torch

from eligsir_o3d import Config
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import SH_C0
from eligsir_o3d.run.pipeline import RunOptions, run_mapping
from eligsir_o3d.visual.pictures import comparison_picture, spread, write_heldout_pictures
from eligsir_o3d.visual.splats import read_splats
from eligsir_o3d.visual.video import smooth_path

from helpers.visual_fixtures import ViewerConnection, write_third_party_ply, write_wall_map


def test_splats_of_a_third_party_sh3_ply(tmp_path):
    """A PLY as the original 3DGS code writes it (SH degree 3, no comment): DC colour, R diag(s^2) R^T."""
    path, raw = write_third_party_ply(tmp_path / "point_cloud.ply")
    s = read_splats(path)
    assert s.sh_degree == 3 and len(s) == len(raw["x"])
    np.testing.assert_allclose(s.centers, np.stack([raw["x"], raw["y"], raw["z"]], 1), atol=1e-6)
    dc = np.stack([raw[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_allclose(s.rgbs, np.clip(0.5 + SH_C0 * dc, 0, 1), atol=1e-6)
    np.testing.assert_allclose(s.opacities[:, 0], 1 / (1 + np.exp(-raw["opacity"])), atol=1e-6)
    # Gaussian 0 is rotated 90 degrees about z: its x and y extents swap
    sc = np.exp(np.stack([raw[f"scale_{i}"][0] for i in range(3)]))
    np.testing.assert_allclose(np.diag(s.covariances[0]), [sc[1] ** 2, sc[0] ** 2, sc[2] ** 2], rtol=1e-5)
    cov = s.covariances
    np.testing.assert_allclose(cov, cov.transpose(0, 2, 1), atol=1e-9)
    assert (np.linalg.eigvalsh(cov.astype(np.float64)) > 0).all()


def test_comparison_picture_layout_and_errors():
    h, w = 48, 64
    ref = torch.rand(h, w, 3)
    depth = torch.full((h, w), 2.0)
    depth[:, :8] = 0.0  # no sensor depth there
    alpha = torch.ones(h, w)
    perfect = comparison_picture(ref, depth, ref, depth, alpha, "t")
    assert perfect.shape[1] == 3 * w and perfect.dtype == np.uint8
    title = perfect.shape[0] - 2 * h
    top = perfect[title:title + h]
    bottom = perfect[title + h:]
    low = slice(h // 2, h), slice(w // 2, w)  # away from the labels
    assert np.abs(top[:, :w][low].astype(int) - np.asarray(ref[low] * 255).round().astype(int)).max() <= 1
    assert np.array_equal(top[:, w:2 * w][low], top[:, :w][low])  # the render panel shows the render
    perfect_err = top[:, 2 * w:][low].astype(float).mean()
    worse = comparison_picture(ref, depth, (ref + 0.2).clamp(0, 1), depth + 0.2, alpha, "t")
    worse_err = worse[title:title + h, 2 * w:][low].astype(float).mean()
    assert worse_err > perfect_err + 40  # the error panel lights up
    assert np.all(bottom[h // 2:, :8] == 0)  # no sensor depth: black
    derr = worse[title + h:, 2 * w:][h // 2:, w // 2:].astype(float).mean()
    assert derr > bottom[h // 2:, 2 * w:][:, w // 2:].astype(float).mean() + 40


def test_heldout_pictures_are_spread_and_named_by_frame(tmp_path):
    from types import SimpleNamespace

    cam = Camera(32, 24, 30.0, 30.0, 15.5, 11.5)
    frames = [SimpleNamespace(index=i, timestamp=i / 30, color=torch.rand(24, 32, 3), depth=torch.ones(24, 32),
                              camera=cam, T_world_cam=np.eye(4)) for i in range(3, 40, 4)]
    assert spread(10, 4) == [0, 3, 6, 9] and spread(3, 6) == [0, 1, 2] and spread(0, 6) == []

    def render(f):
        return SimpleNamespace(color=f.color, depth=f.depth, alpha=torch.ones(24, 32))

    paths = write_heldout_pictures(tmp_path, frames, render, count=4)
    assert [p.name for p in paths] == ["000003.png", "000015.png", "000027.png", "000039.png"]
    import cv2

    assert cv2.imread(str(paths[0])).shape == (2 * 24 + 34, 3 * 32, 3)


def test_smooth_path_removes_jitter_and_keeps_rotations_valid():
    rng = np.random.default_rng(0)
    poses = []
    for k in range(80):
        T = np.eye(4)
        a = 0.02 * k + 0.03 * rng.standard_normal()
        T[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
        T[:3, 3] = [0.01 * k, 0.005 * rng.standard_normal(), 0.0]
        poses.append(T)
    out = smooth_path(poses, n_out=50)
    assert len(out) == 50
    for T in out:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    jitter = lambda ps: np.abs(np.diff([T[1, 3] for T in ps], 2)).mean()  # noqa: E731
    assert jitter(out) < 0.2 * jitter(poses)
    assert abs(out[0][0, 3] - 0.0) < 0.05 and abs(out[-1][0, 3] - 0.79) < 0.05  # it still spans the path


def test_render_command_writes_frames_and_a_video(tmp_path):
    import cv2
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    # SH degree 0: rendering view-dependent colour is gaussians.colors()'s business, tested with the renderers
    map_ply, traj = write_wall_map(tmp_path / "run", sh_degree=0)
    r = CliRunner().invoke(app, ["render", str(map_ply), "--poses", str(traj), "--out", str(tmp_path / "frames"),
                                 "--video", str(tmp_path / "fly.mp4"), "--scale", "0.25"])
    assert r.exit_code == 0, r.output
    frames = sorted((tmp_path / "frames").glob("*.png"))
    n_poses = sum(1 for ln in traj.read_text().splitlines() if not ln.startswith("#"))
    assert len(frames) == n_poses
    img = cv2.imread(str(frames[0]))[..., ::-1]
    assert img.shape == (120, 160, 3)
    assert img[40:80, 50:110].mean() > 60  # the wall in front of the camera is drawn, not the black background
    cap = cv2.VideoCapture(str(tmp_path / "fly.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == n_poses and cap.read()[0]
    bad = CliRunner().invoke(app, ["render", str(map_ply), "--poses", str(tmp_path / "none.txt"),
                                   "--out", str(tmp_path / "f2")])
    assert bad.exit_code == 2 and "none.txt" in bad.output and "Traceback" not in bad.output


def _cfg():
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 3, 10
    return cfg


def _opts(**kw):
    return RunOptions(**{**dict(max_frames=16, holdout_every=4, eval_every=0, progress=False, plots=False), **kw})


def test_map_writes_pictures_unless_told_not_to(tmp_path):
    import cv2

    m = run_mapping("synthetic", tmp_path / "a", _cfg(), _opts())
    pics = sorted((tmp_path / "a" / "heldout").glob("*.png"))
    assert len(pics) == 4  # every held-out view of this short run (frames 2, 6, 10, 14)
    assert [p.stem for p in pics] == [f"{i:06d}" for i in (2, 6, 10, 14)]
    cap = cv2.VideoCapture(str(tmp_path / "a" / "flythrough.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12 and cap.read()[0]  # one frame per mapped pose
    saved = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert saved["pictures"]["heldout"] == [f"heldout/{p.name}" for p in pics]
    assert saved["pictures"]["flythrough"] == "flythrough.mp4" and m["pictures"]["flythrough_frames"] == 12
    run_mapping("synthetic", tmp_path / "b", _cfg(), _opts(pictures=False))
    assert not (tmp_path / "b" / "heldout").exists() and not (tmp_path / "b" / "flythrough.mp4").exists()


def test_live_view_pushes_while_mapping_and_leaves_the_run_unchanged(tmp_path):
    pytest.importorskip("viser")
    from eligsir_o3d.visual.live import LiveView

    base = run_mapping("synthetic", tmp_path / "a", _cfg(), _opts(pictures=False))
    live = LiveView(port=0, every_s=1e-3)  # push at every update: the most the viewer can do
    push = live.push

    def slow_push(rec):  # a viewer far slower than the real one: its time must not count as mapping
        time.sleep(0.2)
        push(rec)

    live.push = slow_push
    client = ViewerConnection(live.url)
    try:
        t0 = time.monotonic()
        while not live.viewer.server.get_clients() and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        viewed = run_mapping("synthetic", tmp_path / "b", _cfg(), _opts(pictures=False, view=live))
        assert live.pushes >= 20 and client.received > 0
        live.show_results(tmp_path / "b")  # the final map with its cameras replaces the live scene
    finally:
        client.close()
        live.close()
    # the deterministic run is the same run with the viewer attached: same updates, same map, same scores
    for key in ("updates", "gaussians", "supervised_mpix"):
        assert viewed[key] == base[key], key
    assert viewed["heldout"]["psnr"] == pytest.approx(base["heldout"]["psnr"], abs=1e-6)
    # 0.2 s a push, >= 20 pushes: at least 4 s of viewer work, none of it billed as mapping (half as a margin
    # for the noise of a loaded machine)
    assert viewed["mapping_time_s"] < base["mapping_time_s"] + 0.2 * live.pushes / 2


def test_viewer_layers_cameras_and_bad_input(tmp_path):
    pytest.importorskip("viser")
    import open3d as o3d
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app
    from eligsir_o3d.visual.viewer import open_map_viewer

    map_ply, traj = write_wall_map(tmp_path / "run")
    box = o3d.geometry.TriangleMesh.create_box(0.5, 0.5, 0.5)
    box.paint_uniform_color([0.2, 0.6, 0.9])
    o3d.io.write_triangle_mesh(str(tmp_path / "run" / "mesh.ply"), box)
    o3d.io.write_point_cloud(str(tmp_path / "run" / "cloud.ply"), box.sample_points_uniformly(200))
    viewer = open_map_viewer(map_ply, port=0, max_cameras=5)
    try:
        assert set(viewer._toggles) == {"Gaussians", "Trajectory", "Cameras", "Mesh", "Point cloud"}
        assert viewer._toggles["Mesh"].value is False and viewer._handles["Mesh"].visible is False
        viewer._toggles["Mesh"].value = True  # what ticking the box does
        time.sleep(0.5)
        assert viewer._handles["Mesh"].visible is True
        assert len(viewer._handles["Cameras"].handles) == 5 and len(viewer.poses) == 8
        np.testing.assert_allclose(viewer.server.initial_camera.up, [0, -1, 0])  # OpenCV: up is -y
    finally:
        viewer.close()
    (tmp_path / "run" / "mesh.ply").write_text("not a mesh")
    r = CliRunner().invoke(app, ["view", str(map_ply), "--port", "0"])
    assert r.exit_code == 2 and "mesh.ply" in r.output and "Traceback" not in r.output, r.output
    r = CliRunner().invoke(app, ["view", str(tmp_path / "missing.ply")])
    assert r.exit_code == 2 and "missing.ply: no such file" in r.output, r.output
