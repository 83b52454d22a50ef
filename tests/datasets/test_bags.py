"""ROS 1 / ROS 2 (sqlite3, mcap) bags written from real 7-Scenes frames with rosbags, read back by open_sequence."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.datasets import DatasetError, open_sequence

pytest.importorskip("rosbags")
from eligsir_o3d.datasets.writers import write_rosbag  # noqa: E402

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")
N = 6
T0 = 1.7e9


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


def _same_frames(seq, src, n=N, depth_tol=0.0, t0=T0, poses=True):
    assert len(seq) == n
    assert seq.camera == src.camera
    for i in range(n):
        a, b = seq[i], src[i]
        assert a.timestamp == pytest.approx(b.timestamp + t0, abs=1e-6)
        np.testing.assert_array_equal(a.rgbd.color.as_tensor().numpy(), b.rgbd.color.as_tensor().numpy())
        da = a.rgbd.depth.as_tensor().numpy()[..., 0].astype(np.float64) / seq.depth_scale
        db = b.rgbd.depth.as_tensor().numpy()[..., 0].astype(np.float64) / src.depth_scale
        np.testing.assert_allclose(da, db, atol=depth_tol)
        if poses:
            np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)
        else:
            assert a.T_world_cam is None


@pytest.mark.parametrize("ros,storage,color,depth,poses", [
    (1, None, "raw", "16UC1", "pose"),
    (2, "sqlite3", "raw", "32FC1", "odometry"),
    (2, "mcap", "jpeg", "16UC1", "pose"),
])
def test_bag_round_trip(tmp_path, src, ros, storage, color, depth, poses):
    out = tmp_path / ("x.bag" if ros == 1 else "x")
    write_rosbag(src, out, ros=ros, storage=storage or "sqlite3", frames=range(N), color=color, depth=depth,
                 poses=poses)
    seq = open_sequence(out)
    assert seq.format == f"ros{ros}"
    assert seq.depth_scale == (1.0 if depth == "32FC1" else 1000.0)
    _same_frames(seq, src, depth_tol=1e-6 if depth == "32FC1" else 0.0)
    assert seq.topics["pose"] == "/camera/pose"
    if storage == "mcap":  # the .mcap file itself also opens
        assert len(open_sequence(next(out.glob("*.mcap")))) == N


def test_tf_poses_between_named_frames(tmp_path, src):
    out = tmp_path / "tf.bag"
    write_rosbag(src, out, ros=1, frames=range(N), poses="tf")
    seq = open_sequence(out, pose_frames="world:camera_color_optical_frame")  # world->link (tf) + link->optical
    _same_frames(seq, src)
    assert seq.poses is not None
    with pytest.raises(DatasetError, match="no tf chain from 'world' to 'nowhere'.*camera_link"):
        open_sequence(out, pose_frames="world:nowhere")


def test_bag_without_poses_maps_with_odometry(tmp_path, src, caplog):
    from eligsir_o3d import Config
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    out = tmp_path / "np"
    write_rosbag(src, out, ros=2, frames=range(8), poses=None)
    seq = open_sequence(out)
    assert seq.poses is None and seq.default_pose == "odometry"
    _same_frames(seq, src, n=8, poses=False)
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 1, 2
    with caplog.at_level("INFO", logger="eligsir_o3d"):
        m = run_mapping(str(out), tmp_path / "run", cfg, RunOptions(holdout_every=4, eval_every=0, progress=False,
                                                                    plots=False))
    assert "has no poses: tracking with the odometry pose source" in caplog.text
    assert m["frames_source"] == 6 and m["skipped_frames"] == [] and m["pose_source"] == "odometry"
    assert len((tmp_path / "run" / "trajectory.txt").read_text().splitlines()) == 1 + 6


def test_ambiguous_topics_list_candidates_and_options_choose(tmp_path, src):
    out = tmp_path / "amb.bag"
    write_rosbag(src, out, ros=1, frames=range(3), extra_topics=["/camera2/color/image_raw"])
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    msg = str(e.value)
    assert "2 candidate colour image topics" in msg and "/camera/color/image_raw (Image rgb8)" in msg
    assert "/camera2/color/image_raw (Image rgb8)" in msg and "--rgb-topic" in msg
    seq = open_sequence(out, rgb_topic="/camera2/color/image_raw")
    assert seq.topics["rgb"] == "/camera2/color/image_raw" and len(seq) == 3
    with pytest.raises(DatasetError, match="no topic '/nope'"):
        open_sequence(out, rgb_topic="/nope")


def test_separate_depth_camera_info_is_kept(tmp_path, src):
    dcam = Camera(640, 480, 570.0, 571.0, 321.0, 239.0)
    out = tmp_path / "two"
    write_rosbag(src, out, ros=2, frames=range(3), depth_camera=dcam)
    with pytest.warns(UserWarning, match="cameras differ; depth is registered into the colour camera"):
        seq = open_sequence(out)
    assert seq.color_intrinsic == src.camera and seq.depth_intrinsic == dcam
    assert not seq.cameras.registered
    # frames are on the colour camera, their depth registered into it at read time
    assert seq.camera == src.camera and seq.depth_camera == dcam and seq.rig is not None
    from eligsir_o3d.datasets.registration import register_depth

    _, native_depth = seq.read_native(1)
    depth = seq[1].rgbd.depth.as_tensor().numpy()[..., 0]
    assert depth.shape == (src.camera.height, src.camera.width)
    np.testing.assert_array_equal(depth, register_depth(native_depth, dcam, src.camera, np.eye(4),
                                                        depth_scale=seq.depth_scale).astype(depth.dtype))
    assert seq.topics["rgb_info"] == "/camera/color/camera_info"
    assert seq.topics["depth_info"] == "/camera/depth/camera_info"


def test_bad_bags_give_one_line_errors(tmp_path, src):
    good = tmp_path / "good.bag"
    write_rosbag(src, good, ros=1, frames=range(3))
    cut = tmp_path / "cut.bag"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DatasetError, match=r"cut\.bag: cannot read the bag.*truncated"):
        open_sequence(cut)

    nodepth = tmp_path / "nodepth.bag"
    write_rosbag(src, nodepth, ros=1, frames=range(2), write_depth=False)
    with pytest.raises(DatasetError, match=r"nodepth\.bag: no depth image topic found; the bag has: .*image_raw"):
        open_sequence(nodepth)

    weird = tmp_path / "enc"
    write_rosbag(src, weird, ros=2, frames=range(2), depth="16SC1", topics={"depth": "/camera/depth/image_raw"})
    with pytest.raises(DatasetError, match=r"enc .*/camera/depth/image_raw.*depth encoding '16SC1' is not supported"):
        open_sequence(weird)


def test_cli_maps_a_bag_and_reports_bad_ones_without_traceback(tmp_path, src):
    from typer.testing import CliRunner

    import eligsir_o3d as eo3d
    from eligsir_o3d.cli.app import app

    bag = tmp_path / "k.bag"
    write_rosbag(src, bag, ros=1, frames=range(6), extra_topics=["/other/image"])
    cfg = eo3d.Config()
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 1, 0
    cfg.save(tmp_path / "cfg.json")
    common = ["--holdout-every", "3", "--eval-every", "0", "--config", str(tmp_path / "cfg.json"), "-q"]
    runner = CliRunner()
    r = runner.invoke(app, ["map", str(bag), *common, "--out", str(tmp_path / "a")])
    assert r.exit_code == 2 and "Traceback" not in r.output and "--rgb-topic" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    r = runner.invoke(app, ["map", str(bag), *common, "--out", str(tmp_path / "b"), "--rgb-topic", "/other/image"])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m["frames_total"] == 6 and m["pose_source"] == "gt"
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[:5000])
    r = runner.invoke(app, ["map", str(cut), *common, "--out", str(tmp_path / "c")])
    assert r.exit_code == 2 and "Traceback" not in r.output and "cut.bag: cannot read the bag" in r.output, r.output
