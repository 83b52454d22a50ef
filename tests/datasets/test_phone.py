"""Phone captures (Record3D .r3d and EXR + JPG, Stray Scanner, Polycam) written from real 7-Scenes frames and read
back."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d import Config
from eligsir_o3d.datasets import DatasetError, open_sequence
from eligsir_o3d.datasets.phone import PhoneOptions, clean_depth
from eligsir_o3d.run.pipeline import RunOptions, run_mapping
from helpers.messages import one_line

pytest.importorskip("liblzfse")
pytest.importorskip("imageio_ffmpeg")
from eligsir_o3d.datasets.phone_writers import (write_polycam, write_record3d, write_record3d_exr,  # noqa: E402
                                                write_stray)

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")
WRITERS = {"record3d": (write_record3d, "cap.r3d"), "record3d_exr": (write_record3d_exr, "exr"),
           "stray": (write_stray, "stray"), "polycam": (write_polycam, "poly")}
N_MAP = 16


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


def _write(fmt, src, tmp_path, **kw):
    if fmt == "record3d_exr":
        pytest.importorskip("OpenEXR")
    fn, name = WRITERS[fmt]
    return fn(src, tmp_path / name, **kw)


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_round_trip_reads_the_same_frames(tmp_path, src, fmt):
    seq = open_sequence(_write(fmt, src, tmp_path, frames=range(5)))
    assert seq.format == fmt and len(seq) == 5 and seq.camera == src.camera and seq.rig is None
    for i in range(5):
        a, b = seq[i], src[i]
        assert a.timestamp == pytest.approx(b.timestamp, abs=1e-5)
        np.testing.assert_array_equal(a.rgbd.color.as_tensor().numpy(), b.rgbd.color.as_tensor().numpy())
        db = b.rgbd.depth.as_tensor().numpy()[..., 0] / src.depth_scale
        np.testing.assert_allclose(a.rgbd.depth.as_tensor().numpy()[..., 0], np.where(db > 5.0, 0, db), atol=1e-6)
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-6)


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_phone_resolution_depth_is_registered_into_colour(tmp_path, src, fmt):
    seq = open_sequence(_write(fmt, src, tmp_path, frames=range(2), depth_size=(256, 192)))
    assert seq.rig is not None and (seq.depth_camera.width, seq.depth_camera.height) == (256, 192)
    assert seq.camera == src.camera
    d = seq.frame(1).depth.numpy()
    ref = src.frame(1).depth.numpy()
    both = (d > 0) & (ref > 0)
    assert both.mean() > 0.5  # the 256 x 192 samples cover the colour image (3 x 3 colour pixels each)
    assert np.median(np.abs(d[both] - ref[both])) < 0.02


def test_colour_much_larger_than_depth_is_scaled_down(tmp_path, src):
    seq = open_sequence(write_record3d(src, tmp_path / "c.r3d", frames=range(2), depth_size=(256, 192)),
                        color_width=320)
    assert (seq.camera.width, seq.camera.height) == (320, 240)
    assert seq.camera.fx == pytest.approx(src.camera.fx / 2)
    f = seq.frame(1)
    assert f.color.shape == (240, 320, 3) and f.depth.shape == (240, 320) and (f.depth > 0).float().mean() > 0.5


def _cfg() -> Config:
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 20
    return cfg


def _map(path, out, **kw) -> dict:
    return run_mapping(str(path), out, _cfg(), RunOptions(holdout_every=8, eval_every=0, progress=False, plots=False,
                                                          pictures=False, **kw))


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("dir") / "run"
    return _map(SEVEN, out, max_frames=N_MAP), out


@pytest.fixture(scope="module")
def folder_psnr(folder_run):
    return folder_run[0]["heldout"]["psnr"]


def _map_centre(run_dir) -> np.ndarray:
    from plyfile import PlyData

    v = PlyData.read(str(run_dir / "map.ply"), mmap=False)["vertex"]
    return np.median(np.stack([v["x"], v["y"], v["z"]], axis=1), axis=0)


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_round_trip_maps_like_the_folder(tmp_path, src, folder_psnr, fmt):
    m = _map(_write(fmt, src, tmp_path, frames=range(N_MAP)), tmp_path / "run")
    assert m["pose_source"] == "gt" and m["frames_heldout"] == N_MAP // 8
    assert abs(m["heldout"]["psnr"] - folder_psnr) < 0.3, (m["heldout"]["psnr"], folder_psnr)


def test_record3d_poses_need_the_opengl_flip(tmp_path, src, folder_run):
    """A capture written as Record3D writes it (OpenGL camera axes) maps where the folder's map is only because the
    reader flips the axes: the same capture read without the flip (its poses written pre-flipped, so that the
    reader's flip leaves them in OpenGL axes) puts the map elsewhere and scores worse at the true held-out poses."""
    right = write_record3d(src, tmp_path / "gl.r3d", frames=range(N_MAP))
    wrong = write_record3d(src, tmp_path / "cv.r3d", frames=range(N_MAP), gl_axes=False)
    np.testing.assert_allclose(open_sequence(right).poses[3], src.poses[3], atol=1e-6)
    assert np.abs(open_sequence(wrong).poses[3][:3, :3] - src.poses[3][:3, :3]).max() > 0.5
    _map(right, tmp_path / "run_right")
    _map(wrong, tmp_path / "run_wrong")
    centre = _map_centre(folder_run[1])
    assert np.linalg.norm(_map_centre(tmp_path / "run_right") - centre) < 0.05
    assert np.linalg.norm(_map_centre(tmp_path / "run_wrong") - centre) > 0.5


def test_record3d_K_is_column_major(tmp_path, src):
    seq = open_sequence(write_record3d(src, tmp_path / "cm.r3d", frames=range(1)))
    assert (seq.camera.cx, seq.camera.cy) == pytest.approx((src.camera.cx, src.camera.cy))
    with pytest.raises(DatasetError, match=r"rm\.r3d:metadata: K is not a column-major"):
        open_sequence(write_record3d(src, tmp_path / "rm.r3d", frames=range(1), column_major=False))


def test_bad_captures_give_one_line_errors_naming_the_file(tmp_path, src):
    r3d = write_record3d(src, tmp_path / "ok.r3d", frames=range(3))
    cut = tmp_path / "cut.r3d"
    cut.write_bytes(r3d.read_bytes()[: r3d.stat().st_size // 2])
    with pytest.raises(DatasetError) as e:
        open_sequence(cut)
    assert "truncated" in one_line(e, "cut.r3d")

    with pytest.raises(DatasetError) as e:
        open_sequence(write_record3d(src, tmp_path / "nometa.r3d", frames=range(2), metadata=False))
    assert "no metadata" in one_line(e, "nometa.r3d:metadata")

    blob = tmp_path / "blob.r3d"  # frame 1's depth blob holds one row too few
    import liblzfse
    with zipfile.ZipFile(r3d) as zin, zipfile.ZipFile(blob, "w") as zout:
        for item in zin.namelist():
            data = zin.read(item)
            if item == "rgbd/1.depth":
                data = liblzfse.compress(liblzfse.decompress(data)[: -640 * 4])
            zout.writestr(item, data)
    seq = open_sequence(blob)
    with pytest.raises(DatasetError) as e:
        seq[1]
    assert "expected dw x dh = 640x480" in one_line(e, "blob.r3d:rgbd/1.depth")

    stray = write_stray(src, tmp_path / "stray", frames=range(4))
    lines = (stray / "odometry.csv").read_text().splitlines()
    (stray / "odometry.csv").write_text("\n".join(lines[:3]) + "\n")  # header + 2 rows for 4 frames
    with pytest.raises(DatasetError) as e:
        open_sequence(stray)
    assert "poses for 2 frames but the capture has 4" in one_line(e, "odometry.csv")

    poly = write_polycam(src, tmp_path / "poly", frames=range(2))
    cam = next((poly / "keyframes" / "cameras").glob("*.json"))
    data = json.loads(cam.read_text())
    del data["fx"]
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError) as e:
        open_sequence(poly)
    assert "missing field(s) fx" in one_line(e, cam.name)


def test_polycam_prefers_corrected_poses_and_skips_frames_without_pose(tmp_path, src):
    poly = write_polycam(src, tmp_path / "poly", frames=range(4), corrected=True)
    seq = open_sequence(poly)
    np.testing.assert_allclose(seq.poses[2], src.poses[2], atol=1e-6)
    cam = sorted((poly / "keyframes" / "corrected_cameras").glob("*.json"))[1]
    data = json.loads(cam.read_text())
    del data["t_03"]
    cam.write_text(json.dumps(data))
    seq = open_sequence(poly)
    assert len(seq) == 3 and len(seq.skipped_frames) == 1 and cam.name in seq.skipped_frames[0]


def test_polycam_uses_corrected_cameras_only_with_corrected_images(tmp_path, src):
    """The corrected (undistorted) images go with the corrected cameras; without them the raw pair is read, as
    nerfstudio's ns-process-data polycam does (the writer's raw poses are 0.5 m off, to tell them apart)."""
    poly = write_polycam(src, tmp_path / "poly", frames=range(3), corrected=True)
    (poly / "keyframes" / "corrected_images").rename(poly / "keyframes" / "images")
    seq = open_sequence(poly)
    np.testing.assert_allclose(seq.poses[2][:3, 3], src.poses[2][:3, 3] + 0.5, atol=1e-6)


def test_polycam_corrected_images_lose_their_undistortion_border(tmp_path, src):
    poly = write_polycam(src, tmp_path / "crop", frames=range(2), corrected=True)
    seq = open_sequence(poly)  # corrected images: 15 pixels cut from each edge, the depth still covers it all
    c = src.camera
    assert (seq.camera.width, seq.camera.height, seq.camera.cx, seq.camera.cy) == (c.width - 30, c.height - 30,
                                                                                   c.cx - 15, c.cy - 15)
    f, g = seq.frame(1), src.frame(1)
    np.testing.assert_array_equal(f.color.numpy(), g.color.numpy()[15:-15, 15:-15])
    d, ref = f.depth.numpy(), g.depth.numpy()[15:-15, 15:-15]
    both = (d > 0) & (ref > 0)
    assert both.mean() > 0.5 and np.median(np.abs(d[both] - ref[both])) < 1e-3
    assert open_sequence(poly, crop_border=0).camera == c
    with pytest.raises(DatasetError, match="crop_border must be 0 to 239 pixels"):
        open_sequence(poly, crop_border=300)


def test_polycam_as_its_spec_describes_it(tmp_path, src):
    """PolyCam/polyform's README: files named by the keyframe's time in microseconds (no time field in the camera
    JSON), confidence 0 / 127 / 255 for low / medium / high."""
    poly = write_polycam(src, tmp_path / "spec", frames=range(3))
    names = sorted(p.stem for p in (poly / "keyframes" / "cameras").glob("*.json"))
    assert all("timestamp" not in json.loads((poly / "keyframes" / "cameras" / f"{n}.json").read_text())
               for n in names)
    seq = open_sequence(poly)
    np.testing.assert_allclose(seq.timestamps, np.asarray(src.timestamps[:3]) - src.timestamps[0], atol=1e-6)
    conf = np.zeros((480, 640), np.uint8)
    conf[:, :320] = 127  # medium on the left, low on the right
    import cv2

    cv2.imwrite(str(poly / "keyframes" / "confidence" / f"{names[1]}.png"), conf)
    d = seq.frame(1).depth.numpy()
    assert (d[:, :320] > 0).mean() > 0.5 and not (d[:, 320:] > 0).any()  # default: keep medium and high
    with pytest.raises(ValueError, match="no valid measurement"):  # high only: nothing of frame 1 is left
        open_sequence(poly, min_confidence=2).frame(1)


def test_stray_old_odometry_without_timestamp_columns(tmp_path, src):
    stray = write_stray(src, tmp_path / "old", frames=range(3), header="x, y, z, qx, qy, qz, qw")
    seq = open_sequence(stray, fps=60.0)
    assert seq.timestamps[1] == pytest.approx(1 / 60)
    np.testing.assert_allclose(seq.poses[2], src.poses[2], atol=1e-6)


def test_stray_frame_without_depth_does_not_shift_the_rest(tmp_path, src):
    """The app numbers depth, confidence and odometry rows by frame and puts every frame in the video, depth or
    not (strayrobots/scanner DatasetEncoder): a frame the phone gave no depth for is a gap, not a shift."""
    stray = write_stray(src, tmp_path / "gap", frames=range(5))
    (stray / "depth" / "000002.png").unlink()
    (stray / "confidence" / "000002.png").unlink()
    seq = open_sequence(stray)
    assert seq.frame_numbers == [0, 1, 3, 4] and "frame 000002 has no depth" in seq.skipped_frames[0]
    np.testing.assert_array_equal(seq[2].rgbd.color.as_tensor().numpy(), src[3].rgbd.color.as_tensor().numpy())
    np.testing.assert_allclose(seq.poses[2], src.poses[3], atol=1e-6)
    assert seq.timestamps[2] == pytest.approx(src.timestamps[3], abs=1e-5)


def test_stray_2021_npy_depth(tmp_path, src):
    seq = open_sequence(write_stray(src, tmp_path / "npy", frames=range(2), depth_ext="npy"))
    png = open_sequence(write_stray(src, tmp_path / "png", frames=range(2)))
    np.testing.assert_array_equal(seq.frame(1).depth.numpy(), png.frame(1).depth.numpy())
    np.save(seq.path / "depth" / "000001.npy", np.zeros((4, 4), np.float32))
    with pytest.raises(DatasetError) as e:
        seq[1]
    assert "not 16-bit single-channel millimetres (got float32 (4, 4))" in one_line(e, "000001.npy")


def test_stray_hevc_video_as_the_app_writes_it(tmp_path, src):
    seq = open_sequence(write_stray(src, tmp_path / "hevc", frames=range(3), hevc=True))
    for i in (2, 0):  # backwards: the decoder is reopened
        a = seq[i].rgbd.color.as_tensor().numpy().astype(float)
        b = src[i].rgbd.color.as_tensor().numpy().astype(float)
        assert 10 * np.log10(255.0 ** 2 / np.mean((a - b) ** 2)) > 30.0


def test_confidence_and_range_drop_depth():
    d = np.array([[1.0, 2.0, 6.0, np.nan]], dtype=np.float32)
    conf = np.array([[0, 1, 2, 2]], dtype=np.uint8)
    np.testing.assert_array_equal(clean_depth(d, conf, PhoneOptions()), [[0, 2.0, 0, 0]])
    np.testing.assert_array_equal(clean_depth(d, conf, PhoneOptions(min_confidence=0, max_depth=10)),
                                  [[1.0, 2.0, 6.0, 0]])
    with pytest.raises(DatasetError, match="min_confidence"):
        PhoneOptions(min_confidence=3)


def test_new_layouts_are_listed():
    from eligsir_o3d.datasets import list_formats

    assert {"record3d", "record3d_exr", "stray", "polycam"} <= set(list_formats())
