"""RealSense .bag: written in librealsense's layout from real 7-Scenes frames; read by our reader and by Open3D's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from eligsir_o3d.datasets import DatasetError, open_sequence

pytest.importorskip("rosbags")
from eligsir_o3d.datasets.writers import write_realsense_bag  # noqa: E402

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")
N = 5


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


@pytest.fixture(scope="module")
def bag(src, tmp_path_factory):
    return write_realsense_bag(src, tmp_path_factory.mktemp("rs") / "capture.bag", frames=range(N))


def test_realsense_bag_reads_back_exactly(bag, src):
    seq = open_sequence(bag)
    assert seq.format == "realsense" and len(seq) == N and seq.poses is None and seq.default_pose == "odometry"
    assert seq.camera == src.camera and seq.depth_scale == 1000.0
    np.testing.assert_allclose(seq.timestamps, 1.0 + src.timestamps[:N], atol=1e-6)
    np.testing.assert_allclose(seq.T_color_depth, np.eye(4), atol=1e-12)
    for i in range(N):
        np.testing.assert_array_equal(seq[i].rgbd.color.as_tensor().numpy(), src[i].rgbd.color.as_tensor().numpy())
        np.testing.assert_array_equal(seq[i].rgbd.depth.as_tensor().numpy(), src[i].rgbd.depth.as_tensor().numpy())


def test_open3d_rsbagreader_accepts_the_bag_and_agrees(bag, src):
    reader = o3d.t.io.RSBagReader()
    assert reader.open(str(bag))
    md = reader.metadata
    assert (md.width, md.height) == (640, 480) and md.fps == 30.0
    assert md.depth_scale == pytest.approx(1000.0, rel=1e-6)
    np.testing.assert_allclose(md.intrinsics.intrinsic_matrix, src.camera.K)
    assert md.stream_length_usec == pytest.approx((N - 1) / 30 * 1e6, abs=10)
    ours = open_sequence(bag)
    got = []
    while not reader.is_eof():
        f = reader.next_frame()
        if not f.is_empty():
            got.append((f.color.as_tensor().numpy().copy(), f.depth.as_tensor().numpy().copy()))
    reader.close()
    assert got  # Open3D streams through a frame queue: it drops the first frameset, and more under load
    for color, depth in got:  # each frame Open3D returns is one of ours, pixel for pixel
        k = int(np.argmin([np.abs(color.astype(int) - ours[i].rgbd.color.as_tensor().numpy()).mean()
                           for i in range(N)]))
        np.testing.assert_array_equal(color, ours[k].rgbd.color.as_tensor().numpy())
        np.testing.assert_array_equal(depth, ours[k].rgbd.depth.as_tensor().numpy())


def test_realsense_bag_with_a_pose_topic(src, tmp_path):
    seq = open_sequence(write_realsense_bag(src, tmp_path / "posed.bag", frames=range(3), poses=True))
    assert seq.format == "realsense" and seq.topics["pose"] == "/camera/pose"
    for i in range(3):
        np.testing.assert_allclose(seq[i].T_world_cam, src[i].T_world_cam, atol=1e-9)


def test_realsense_bag_without_colour_stream_is_a_clear_error(src, tmp_path):
    from eligsir_o3d.datasets import rsbag

    bag = write_realsense_bag(src, tmp_path / "x.bag", frames=range(2))
    with pytest.raises(DatasetError, match=r"x\.bag: RealSense bag without a infrared stream"):
        rsbag._stream_topics(["/device_0/sensor_0/Depth_0/image/data"], "Infrared", bag)
