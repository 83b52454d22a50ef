"""ScanNet .sens: written from real 7-Scenes frames, read back lazily; bad poses and bad files."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from eligsir_o3d.datasets import DatasetError, open_sequence
from eligsir_o3d.datasets.writers import write_sens

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


def test_sens_round_trip_skips_bad_poses(tmp_path, src):
    path = write_sens(src, tmp_path / "scene.sens", frames=range(6), bad_pose_frames=[2, 4])
    with pytest.warns(UserWarning, match=r"left out 2 of 6 frames with an invalid \(-inf/NaN\) pose: 2, 4"):
        seq = open_sequence(path)
    assert seq.format == "scannet" and len(seq) == 4 and seq.bad_pose_frames == [2, 4]
    assert seq.dropped_unassociated == 2 and seq.depth_scale == 1000.0
    for k, i in enumerate([0, 1, 3, 5]):
        a, b = seq[k], src[i]
        assert a.timestamp == pytest.approx(b.timestamp, abs=1e-6)
        np.testing.assert_array_equal(a.rgbd.color.as_tensor().numpy(), b.rgbd.color.as_tensor().numpy())
        np.testing.assert_array_equal(a.rgbd.depth.as_tensor().numpy(), b.rgbd.depth.as_tensor().numpy())
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-6)  # float32 in the file


def test_sens_two_cameras_are_kept(tmp_path, src):
    path = write_sens(src, tmp_path / "hi.sens", frames=range(2), color_size=(1296, 968))
    seq = open_sequence(path)
    assert (seq.color_intrinsic.width, seq.color_intrinsic.height) == (1296, 968)
    assert seq.color_intrinsic.fx == pytest.approx(src.camera.fx * 1296 / 640, rel=1e-6)
    assert seq.depth_intrinsic == src.camera and seq.depth_camera == src.camera
    np.testing.assert_allclose(seq.T_color_depth, np.eye(4))
    color, depth = seq.read_native(1)
    assert color.shape == (968, 1296, 3) and depth.shape == (480, 640)
    # frames are on the colour camera scaled to the depth width, with depth registered into it
    assert seq.camera == seq.color_intrinsic.scaled(640 / 1296) and seq.rig is not None
    frame = seq[1].rgbd.color.as_tensor().numpy()
    assert frame.shape == (seq.camera.height, seq.camera.width, 3) == (478, 640, 3)
    ref = cv2.resize(src[1].rgbd.color.as_tensor().numpy(), (640, 478), interpolation=cv2.INTER_AREA)
    assert np.abs(frame.astype(int) - ref).mean() < 4.0
    reg = seq[1].rgbd.depth.as_tensor().numpy()[..., 0]
    assert reg.shape == (478, 640)
    assert (reg > 0).mean() > 0.9 * (depth > 0).mean()  # registration leaves no sampling holes


def test_sens_reads_lazily_by_offset(tmp_path, src, monkeypatch):
    path = write_sens(src, tmp_path / "lazy.sens", frames=range(5))
    seq = open_sequence(path)
    reads = []
    real_open = open

    def spy(p, mode="r", *a, **kw):
        f = real_open(p, mode, *a, **kw)
        if str(p) == str(path):
            orig = f.read
            f.read = lambda n=-1: (reads.append(n), orig(n))[1]
        return f

    monkeypatch.setattr("builtins.open", spy)
    seq[3]
    assert reads and -1 not in reads and sum(reads) < path.stat().st_size / 3  # only frame 3's bytes


def test_bad_sens_files(tmp_path, src):
    path = write_sens(src, tmp_path / "ok.sens", frames=range(3))
    data = path.read_bytes()
    v5 = tmp_path / "v5.sens"
    v5.write_bytes(struct.pack("<I", 5) + data[4:])
    with pytest.raises(DatasetError, match=r"v5\.sens: \.sens version 5 is not supported"):
        open_sequence(v5)
    cut = tmp_path / "cut.sens"
    cut.write_bytes(data[: len(data) - 1000])
    with pytest.raises(DatasetError, match=r"cut\.sens: frame 2 of 3 runs past the end of the file"):
        open_sequence(cut)
    head = tmp_path / "head.sens"
    head.write_bytes(data[:100])
    with pytest.raises(DatasetError, match=r"head\.sens: file ends inside the header"):
        open_sequence(head)


def test_bad_pose_frames_are_reported_by_the_pipeline(tmp_path, src):
    from eligsir_o3d import Config
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    path = write_sens(src, tmp_path / "s.sens", frames=range(7), bad_pose_frames=[3])
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 1, 0
    with pytest.warns(UserWarning, match="left out 1 of 7"):
        m = run_mapping(str(path), tmp_path / "run", cfg, RunOptions(holdout_every=3, eval_every=0, progress=False,
                                                                     plots=False))
    assert m["frames_total"] == 6
    assert m["skipped_frames"] == ["s.sens frame 3 (in the file): invalid (-inf/NaN) pose, left out"]
