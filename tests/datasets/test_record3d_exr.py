"""Record3D's EXR + JPG export: layout as its author and nerfstudio describe it, written from real 7-Scenes frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d.datasets import DatasetError, open_sequence
from helpers.messages import one_line

OpenEXR = pytest.importorskip("OpenEXR")
from eligsir_o3d.datasets.phone_writers import write_record3d_exr  # noqa: E402

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


def test_export_folder_or_its_exr_rgbd_folder(tmp_path, src):
    out = write_record3d_exr(src, tmp_path / "2024-05-01--10-00-00", frames=range(3))
    for path in (out, out / "EXR_RGBD"):
        seq = open_sequence(path)
        assert seq.format == "record3d_exr" and len(seq) == 3 and seq.camera == src.camera
        np.testing.assert_allclose(seq.poses[2], src.poses[2], atol=1e-6)  # OpenGL axes turned into OpenCV's
    d = OpenEXR.File(str(out / "EXR_RGBD" / "depth" / "1.exr"), separate_channels=True).channels()
    assert list(d) == ["R"] and d["R"].pixels.dtype == np.float32  # one float32 channel "R", as Record3D writes


def test_lone_channel_of_another_name_is_read(tmp_path, src):
    seq = open_sequence(write_record3d_exr(src, tmp_path / "y", frames=range(2), channel="Y"))
    np.testing.assert_array_equal(seq.frame(1).depth.numpy(), open_sequence(
        write_record3d_exr(src, tmp_path / "r", frames=range(2))).frame(1).depth.numpy())


def test_half_float_piz_depth_is_read(tmp_path, src):
    out = write_record3d_exr(src, tmp_path / "half", frames=range(2)) / "EXR_RGBD"
    full = open_sequence(out).frame(1).depth.numpy()
    d = OpenEXR.File(str(out / "depth" / "1.exr"), separate_channels=True).channels()["R"].pixels
    with OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"R": d.astype(np.float16)}) as f:  # another writer's choice: 16-bit floats, PIZ
        f.write(str(out / "depth" / "1.exr"))
    half = open_sequence(out).frame(1).depth.numpy()
    assert half.dtype == np.float32 and np.abs(half - full).max() < 5e-3  # float16 keeps ~3 decimal digits


def test_per_frame_intrinsics_median_is_the_camera(tmp_path, src):
    c = src.camera
    coeffs = [[c.fx * k, c.fy * k, c.cx, c.cy] for k in (0.99, 1.0, 1.02)]  # focus breathing, frame by frame
    seq = open_sequence(write_record3d_exr(src, tmp_path / "pf", frames=range(3), per_frame_intrinsics=coeffs))
    assert (seq.camera.fx, seq.camera.fy) == pytest.approx((c.fx, c.fy))
    bad = write_record3d_exr(src, tmp_path / "pfbad", frames=range(1), per_frame_intrinsics=[[c.fx, c.fy, c.cx]])
    with pytest.raises(DatasetError) as e:
        open_sequence(bad)
    assert "perFrameIntrinsicCoeffs must be [fx, fy, cx, cy]" in one_line(e, "metadata.json")


def test_frames_without_depth_or_pose_are_left_out(tmp_path, src):
    out = write_record3d_exr(src, tmp_path / "gaps", frames=range(5)) / "EXR_RGBD"
    (out / "depth" / "2.exr").unlink()
    meta = json.loads((out / "metadata.json").read_text())
    meta["poses"][3] = [0, 0, 0, 0, 0, 0, 0]  # lost tracking: a zero quaternion
    (out / "metadata.json").write_text(json.dumps(meta))
    (out / "rgb" / "4(1).jpg").write_bytes((out / "rgb" / "4.jpg").read_bytes())  # a duplicate copy: ignored
    seq = open_sequence(out)
    assert seq.frame_numbers == [0, 1, 4] and len(seq.skipped_frames) == 2
    assert "2.jpg: no depth/2.exr" in seq.skipped_frames[0] and "3.jpg: no pose" in seq.skipped_frames[1]
    np.testing.assert_allclose(seq.poses[2], src.poses[4], atol=1e-6)


def test_bad_exports_give_one_line_errors_naming_the_file(tmp_path, src):
    out = write_record3d_exr(src, tmp_path / "bad", frames=range(3)) / "EXR_RGBD"
    exr = out / "depth" / "1.exr"
    exr.write_bytes(exr.read_bytes()[:200])  # truncated
    seq = open_sequence(out)
    with pytest.raises(DatasetError) as e:
        seq[1]
    assert "not a readable EXR image" in one_line(e, "1.exr")

    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"G": np.ones((4, 4), np.float32), "B": np.ones((4, 4), np.float32)}) as f:
        f.write(str(out / "depth" / "2.exr"))
    with pytest.raises(DatasetError) as e:
        seq[2]
    assert "no depth channel" in one_line(e, "2.exr") and "the file has B, G" in str(e.value)

    meta = json.loads((out / "metadata.json").read_text())
    meta["dw"] = 256
    (out / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    assert "metadata.json says dw x dh = 256x480" in one_line(e, "0.exr")

    del meta["K"]
    (out / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    assert "missing field(s) K" in one_line(e, "metadata.json")

    (out / "metadata.json").write_text("{not json")
    with pytest.raises(DatasetError) as e:
        open_sequence(out, kind="record3d_exr")
    assert "not valid JSON" in one_line(e, "metadata.json")


def test_confidence_option_is_refused_and_depth_range_kept(tmp_path, src):
    out = write_record3d_exr(src, tmp_path / "opt", frames=range(2))
    with pytest.raises(DatasetError, match="unknown option.*min_confidence.*record3d_exr"):
        open_sequence(out, min_confidence=2)
    near = open_sequence(out, max_depth=1.0).frame(1).depth.numpy()
    assert near.max() <= 1.0 and (near > 0).any()
