"""Two-camera sequences: depth registered into the colour camera, the sidecar's colour block, calibrate-color."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from typer.testing import CliRunner

from eligsir_o3d.core.camera import Camera, invert_pose, pose_to_tum
from eligsir_o3d.cli.app import app
from eligsir_o3d.datasets.color_calibration import calibrate_color, choose_pairs
from eligsir_o3d.datasets import DatasetError, RGBDSequence, SyntheticRoom, open_sequence
from eligsir_o3d.datasets.registration import TwoCameraRig, read_color_block, register_depth

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
SEVEN = DATA / "7scenes_redkitchen_jpg1000"
SUN3D = DATA / "sun3d_mit76_studyroom_f0935"
needs_data = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")

W, H = 160, 120
COLOR_CAM = Camera(W, H, 112.0, 112.0, 85.5, 57.5)  # the room's depth camera is f = 128, centred


@pytest.fixture(scope="module")
def room() -> SyntheticRoom:
    return SyntheticRoom(n_frames=120, width=W, height=H)


def write_two_camera_room(root: Path, room: SyntheticRoom, color_cam: Camera, n: int = 14,
                          color_block: bool = False) -> Path:
    """The synthetic room seen by two co-located cameras: depth through the room's camera, colour through
    ``color_cam``; a plain folder whose intrinsics.json holds the depth camera (and the colour block if asked)."""
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = []
    for i in range(n):
        T = room.poses[i]
        _, depth = room.render(T)
        color, _ = room.render(T, camera=color_cam)
        o3d.t.io.write_image(str(root / "color" / f"{i:06d}.png"),
                             o3d.t.geometry.Image(np.round(color * 255).astype(np.uint8)))
        o3d.t.io.write_image(str(root / "depth" / f"{i:06d}.png"),
                             o3d.t.geometry.Image(np.round(depth * 1000).astype(np.uint16)[..., None]))
        t, q = pose_to_tum(T)
        lines.append(f"{i / 30:.6f} " + " ".join(f"{x:.9f}" for x in (*t, *q)))
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    d = room.camera
    sidecar = {"width": d.width, "height": d.height, "fx": d.fx, "fy": d.fy, "cx": d.cx, "cy": d.cy,
               "depth_scale": 1000.0}
    if color_block:
        sidecar["color"] = {"fx": color_cam.fx, "fy": color_cam.fy, "cx": color_cam.cx, "cy": color_cam.cy}
    (root / "intrinsics.json").write_text(json.dumps(sidecar))
    return root


# -- register_depth ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("color_cam, T_cd", [
    (COLOR_CAM, None),  # wider colour field of view, shifted principal point
    (Camera(2 * W, 2 * H, 256.0, 256.0, 159.5, 119.5), None),  # colour finer than depth: footprint 2
    (Camera(W, H, 120.0, 120.0, 79.5, 59.5), "moved"),  # 5 cm apart, slightly turned
])
def test_registered_depth_is_the_colour_cameras_depth(room, color_cam, T_cd):
    if T_cd == "moved":
        c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
        T_cd = np.array([[c, 0, s, -0.05], [0, 1, 0, 0.01], [-s, 0, c, 0.0], [0, 0, 0, 1.0]])
    T_wd = room.poses[5]
    _, depth = room.render(T_wd)
    T_wc = T_wd if T_cd is None else T_wd @ invert_pose(T_cd)
    _, truth = room.render(T_wc, camera=color_cam)  # what a depth sensor at the colour camera would measure
    reg = register_depth(np.round(depth * 1000).astype(np.uint16), room.camera, color_cam, T_cd, depth_scale=1000.0)
    assert reg.dtype == np.uint16 and reg.shape == (color_cam.height, color_cam.width)
    both = (reg > 0) & (truth > 0)
    err = np.abs(reg[both] / 1000.0 - truth[both])
    # pixel-centre snapping on slanted surfaces only (half a pixel is ~1 cm at 3 m here); without registration
    # (or without the extrinsic) the median is 2-11 cm
    assert np.median(err) < 0.008
    assert np.mean(err < 0.05) > 0.98
    # where each colour pixel's ray meets the depth image (ignoring the small extrinsic)
    d = room.camera
    v, u = np.mgrid[0:color_cam.height, 0:color_cam.width]
    ud = (u - color_cam.cx) / color_cam.fx * d.fx + d.cx
    vd = (v - color_cam.cy) / color_cam.fy * d.fy + d.cy
    margin = 2 if T_cd is None else 8

    def within(m):
        return (ud >= -0.5 + m) & (ud <= d.width - 0.5 - m) & (vd >= -0.5 + m) & (vd <= d.height - 0.5 - m)

    # colour pixels outside the depth camera's view are no measurement (0), not filled in
    outside = ~within(-margin)
    assert np.all(reg[outside] == 0)
    assert outside.any() == (color_cam.fx < d.fx) or T_cd is not None
    # inside it nearly every colour pixel gets a depth: no sampling holes, even when colour is finer than depth
    inside = within(margin) & (truth > 0)
    assert np.mean(reg[inside] > 0) > 0.97


def test_zbuffer_keeps_the_nearest_depth_and_never_interpolates():
    depth_cam = Camera(4, 1, 100.0, 100.0, 1.5, 0.0)
    color_cam = Camera(1, 1, 1.0, 1.0, 0.0, 0.0)  # every point lands on the single colour pixel
    depth = np.array([[3000, 1200, 0, 2500]], dtype=np.uint16)
    assert register_depth(depth, depth_cam, color_cam).tolist() == [[1200]]
    # two depth pixels three colour pixels apart: the pixels between them stay 0
    cam = Camera(4, 1, 100.0, 100.0, 1.5, 0.0)
    far = register_depth(np.array([[1000, 0, 0, 1000]], dtype=np.uint16), cam, cam)
    assert far.tolist() == [[1000, 0, 0, 1000]]
    metres = register_depth(np.array([[1.25, 0, 0, 2.5]], dtype=np.float32), cam, cam)
    assert metres.dtype == np.float32 and metres.tolist() == [[1.25, 0, 0, 2.5]]


def test_register_depth_is_fast_at_640x480():
    cam = Camera(640, 480, 585.0, 585.0, 320.0, 240.0)
    rig = TwoCameraRig(cam, Camera(640, 480, 525.0, 525.0, 320.0, 240.0))
    depth = np.random.default_rng(0).integers(500, 4000, (480, 640)).astype(np.uint16)
    rig.register(depth, 1000.0)
    t0 = time.perf_counter()
    for _ in range(5):
        rig.register(depth, 1000.0)
    assert (time.perf_counter() - t0) / 5 < 0.25  # ~10-20 ms alone; generous for a loaded 2-core machine


# -- sequences -----------------------------------------------------------------------------------------------
def test_colour_block_registers_frames_at_read_time(tmp_path, room):
    root = write_two_camera_room(tmp_path / "cap", room, COLOR_CAM, n=3, color_block=True)
    seq = open_sequence(root)
    assert seq.camera == COLOR_CAM and seq.depth_camera == room.camera and seq.rig is not None
    frame = seq.frame(1)
    assert frame.camera == COLOR_CAM
    _, truth = room.render(room.poses[1], camera=COLOR_CAM)
    d = frame.depth.numpy()
    both = (d > 0) & (truth > 0)
    assert np.median(np.abs(d[both] - truth[both])) < 0.008
    raw_color, raw_depth = seq.raw_images(1)
    assert raw_depth.shape == (H, W) and raw_color.shape == (H, W, 3)
    assert not np.array_equal(raw_depth, seq[1].rgbd.depth.as_tensor().numpy()[..., 0])
    # ignoring the colour block gives the one-camera sequence of before
    plain = open_sequence(root, register=False)
    assert plain.camera == room.camera and plain.rig is None
    np.testing.assert_array_equal(plain[1].rgbd.depth.as_tensor().numpy()[..., 0], raw_depth)


def test_reader_api_two_cameras_with_extrinsic(room):
    """What a bag or ScanNet reader does: pass the colour camera and extrinsic; poses of the depth camera move."""
    T_cd = np.eye(4)
    T_cd[0, 3] = -0.025
    seq = RGBDSequence(name="rig", path=None, camera=room.camera, depth_scale=1.0, timestamps=[0.0, 0.1],
                       poses=[room.poses[0], room.poses[1]], color_camera=COLOR_CAM, T_color_depth=T_cd)
    np.testing.assert_allclose(seq.poses[0], room.poses[0] @ invert_pose(T_cd))
    seq.ignore_color_camera()
    np.testing.assert_allclose(seq.poses[0], room.poses[0])
    same = RGBDSequence(name="one", path=None, camera=room.camera, depth_scale=1.0, timestamps=[0.0],
                        color_camera=room.camera)
    assert same.rig is None  # identical cameras: nothing to register, results as before


def test_bad_colour_block_names_file_and_field(tmp_path, room):
    root = write_two_camera_room(tmp_path / "cap", room, COLOR_CAM, n=1)
    sidecar = json.loads((root / "intrinsics.json").read_text())
    sidecar["color"] = {"fx": 500.0, "fy": 500.0, "cx": 80.0}
    (root / "intrinsics.json").write_text(json.dumps(sidecar))
    with pytest.raises(DatasetError, match=r"intrinsics\.json.*color.*missing field\(s\) cy"):
        open_sequence(root)
    sidecar["color"] = {"fx": 500.0, "fy": 500.0, "cx": 80.0, "cy": 60.0, "T_color_depth": [1, 2, 3]}
    (root / "intrinsics.json").write_text(json.dumps(sidecar))
    with pytest.raises(DatasetError, match="T_color_depth must be a 4x4"):
        open_sequence(root)
    result = CliRunner().invoke(app, ["map", str(root), "--out", str(tmp_path / "run"), "-q"])
    assert result.exit_code == 2 and "T_color_depth" in result.output and "Traceback" not in result.output


@needs_data
def test_7scenes_colour_block_and_registered_sun3d_unchanged():
    seven = open_sequence(SEVEN)
    assert seven.camera == Camera(640, 480, 525.0, 525.0, 320.0, 240.0)
    assert seven.depth_camera == Camera(640, 480, 585.0, 585.0, 320.0, 240.0)
    reg = seven[100].rgbd.depth.as_tensor().numpy()[..., 0]
    _, raw = seven.raw_images(100)
    assert (reg[:, :20] == 0).all() and (raw[:, 40:60] > 0).mean() > 0.5  # the colour camera sees wider
    assert read_color_block(SUN3D / "intrinsics.json", Camera(640, 480, 1, 1, 0, 0)) is None
    assert open_sequence(SUN3D).rig is None


# -- calibrate-color -----------------------------------------------------------------------------------------
def test_calibration_recovers_a_known_colour_camera(tmp_path, room):
    root = write_two_camera_room(tmp_path / "cap", room, COLOR_CAM, n=14)
    seq = open_sequence(root)
    result = calibrate_color(seq, pairs=4, stride=2, downsample=1)
    assert result.camera.fx == pytest.approx(COLOR_CAM.fx, rel=0.02)
    assert result.camera.fy == pytest.approx(COLOR_CAM.fy, rel=0.02)
    assert result.principal_point and result.camera.cx == pytest.approx(COLOR_CAM.cx, abs=1.5)
    assert result.error < 0.6 * result.error_start
    assert "estimate: fx=" in result.report()


def test_calibrate_color_cli_writes_the_block(tmp_path, room):
    root = write_two_camera_room(tmp_path / "cap", room, COLOR_CAM, n=14)
    result = CliRunner().invoke(app, ["calibrate-color", str(root), "--pairs", "3", "--stride", "4", "--write"])
    assert result.exit_code == 0, result.output
    assert "mean |colour difference|" in result.output and "wrote the colour camera" in result.output
    block = json.loads((root / "intrinsics.json").read_text())["color"]
    assert block["fx"] == pytest.approx(COLOR_CAM.fx, rel=0.03)
    seq = open_sequence(root)
    assert seq.rig is not None and seq.camera.fx == pytest.approx(block["fx"])
    no_poses = tmp_path / "cap2"
    write_two_camera_room(no_poses, room, COLOR_CAM, n=2)
    (no_poses / "poses.txt").unlink()
    bad = CliRunner().invoke(app, ["calibrate-color", str(no_poses)])
    assert bad.exit_code == 2 and "needs poses" in bad.output


def test_pairs_follow_the_motion(room):
    pairs = choose_pairs(room.poses[:30], 3)
    assert len(pairs) == 3 and all(j > i for i, j in pairs)
    assert choose_pairs(room.poses[:30], 2, gap=5) == [(0, 5), (24, 29)]


@needs_data
def test_calibration_on_real_sequences():
    """SUN3D is registered: the estimate is its depth camera's; 7-Scenes' colour camera is near 515-525, not 585."""
    sun3d = open_sequence(SUN3D)
    est = calibrate_color(sun3d, pairs=4, stride=8, principal_point=False)
    assert est.camera.fx == pytest.approx(570.342205, rel=0.02)
    seven = open_sequence(SEVEN)
    est = calibrate_color(seven, pairs=4, stride=8, frames=200, principal_point=False)
    assert 505.0 < est.camera.fx < 540.0
    assert est.start.fx == 585.0 and est.error < 0.85 * est.error_start  # clearly better than the depth camera's


def test_map_sees_the_colour_camera_unless_told_not_to(tmp_path, room, monkeypatch):
    from eligsir_o3d import Config
    from eligsir_o3d.run import pipeline
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    root = write_two_camera_room(tmp_path / "cap", room, COLOR_CAM, n=8, color_block=True)
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 4
    m = run_mapping(str(root), tmp_path / "reg", cfg, RunOptions(holdout_every=4, eval_every=0, progress=False,
                                                                   plots=False))
    assert json.loads((tmp_path / "reg" / "run.json").read_text())["camera"]["fx"] == COLOR_CAM.fx
    assert m["heldout"]["depth_rmse_m"] is not None
    # --no-register reaches open_sequence as register=False (which test_colour_block_registers... checks)
    seen = []

    def fake_run_mapping(path, out, config, opts):
        seen.append(opts.sequence_options)
        raise ValueError("stop here")

    monkeypatch.setattr(pipeline, "run_mapping", fake_run_mapping)
    for extra, want in (([], None), (["--no-register"], {"register": False})):
        r = CliRunner().invoke(app, ["map", str(root), "--out", str(tmp_path / "x"), "-q", *extra])
        assert r.exit_code == 2 and "stop here" in r.output and seen[-1] == want


def test_reader_delivering_the_wrong_depth_size_is_named(room):
    class Odd(RGBDSequence):
        def _read_images(self, i):
            color = np.zeros((H, W, 3), np.uint8)
            return (o3d.t.geometry.Image(o3d.core.Tensor(color)),
                    o3d.t.geometry.Image(o3d.core.Tensor(np.ones((H // 2, W // 2, 1), np.float32))))

    seq = Odd(name="odd", path=None, camera=room.camera, depth_scale=1.0, timestamps=[0.0], color_camera=COLOR_CAM)
    with pytest.raises(DatasetError, match=r"frame 0: cannot register depth.*80x60 but the depth camera is 160x120"):
        seq[0]
