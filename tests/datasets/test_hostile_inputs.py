"""Hostile inputs: phone captures, lists and bags a careful user or an adversary might hand over. Each is read
(the bad frame left out and reported) or refused with one line naming the file and the field; nothing hangs and
nothing is inflated before its size is checked."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d.datasets import DatasetError, open_sequence
from eligsir_o3d.datasets.base import RGBDSequence
from eligsir_o3d.io.inputs import (InputRefused, lzfse_declared_size, read_bytes, read_json, read_zip_member)
from helpers.messages import one_line

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
needs_data = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


@pytest.fixture(scope="module")
def src():
    return open_sequence(SEVEN)


def _r3d_folder(src, tmp_path):
    pytest.importorskip("liblzfse")
    from eligsir_o3d.datasets.phone_writers import write_record3d

    cap = write_record3d(src, tmp_path / "cap.r3d", frames=range(4))
    folder = tmp_path / "cap"
    with zipfile.ZipFile(cap) as z:
        z.extractall(folder)
    return cap, folder


def _meta(folder: Path) -> dict:
    return json.loads((folder / "metadata").read_text())


# -- the one input reader ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("node", ["/dev/zero", "fifo", "dir", "loop"])
def test_reader_refuses_what_is_not_a_regular_file_without_reading_it(tmp_path, node):
    path = Path(node)
    if node == "fifo":
        path = tmp_path / "fifo"
        os.mkfifo(path)
    elif node == "dir":
        path = tmp_path
    elif node == "loop":
        path = tmp_path / "loop.json"
        path.symlink_to(path)
    with pytest.raises(InputRefused) as e:
        read_json(path, "config file")
    msg = one_line(e, str(path))
    assert ("loops" in msg) if node == "loop" else ("not a regular file" in msg)


def test_reader_caps_size_and_depth(tmp_path):
    big = tmp_path / "big.json"
    big.write_bytes(b" " * 2048)
    with pytest.raises(InputRefused, match="more than the"):
        read_bytes(big, "file", max_bytes=1024)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputRefused) as e:
        read_json(deep)
    assert "nested too deeply" in one_line(e, "deep.json")


def test_zip_member_declared_beyond_the_cap_is_not_inflated(tmp_path):
    p = tmp_path / "bomb.zip"
    with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z, z.open("rgbd/0.depth", "w") as f:
        for _ in range(16):
            f.write(bytes(2 ** 20))
    with zipfile.ZipFile(p) as z:
        with pytest.raises(InputRefused) as e:
            read_zip_member(z, "rgbd/0.depth", "bomb.zip:rgbd/0.depth", max_bytes=2 ** 20)
        assert "declares 16 MiB" in one_line(e, "bomb.zip")
        assert len(read_zip_member(z, "rgbd/0.depth", "x", max_bytes=2 ** 24)) == 2 ** 24


def test_lzfse_sizes_are_read_from_the_block_headers():
    liblzfse = pytest.importorskip("liblzfse")
    rng = np.random.default_rng(0)
    for data in (b"", bytes(40), rng.random(100_000).astype(np.float32).tobytes(), bytes(12_000_000)):
        assert lzfse_declared_size(liblzfse.compress(data), "x") == len(data)


@needs_data
def test_r3d_decompression_bomb_is_refused_before_inflating(src, tmp_path):
    """A depth blob whose LZFSE header declares 4 GiB: refused from the header; peak RSS stays flat."""
    cap, folder = _r3d_folder(src, tmp_path)
    bomb = b"bvxn" + (0xFFFFFFF0).to_bytes(4, "little") + (8).to_bytes(4, "little") + bytes(8) + b"bvx$"
    (folder / "rgbd" / "1.depth").write_bytes(bomb)
    seq = open_sequence(folder)
    with pytest.raises(DatasetError) as e:
        seq[1]
    assert "more than the" in one_line(e, "1.depth")
    # a zip member declaring more than the cap, through the .r3d reader, in a fresh process: RSS stays flat
    z = tmp_path / "bomb.r3d"
    with zipfile.ZipFile(cap) as a, zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as b:
        for name in a.namelist():
            if name != "rgbd/2.depth":
                b.writestr(name, a.read(name))
        with b.open("rgbd/2.depth", "w") as f:
            for _ in range(600):
                f.write(bytes(2 ** 20))
    code = ("import resource, sys; from eligsir_o3d.datasets import open_sequence\n"
            "seq = open_sequence(sys.argv[1]); before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
            "try:\n    seq[2]\nexcept ValueError as e:\n    print('REFUSED', e)\n"
            "print('GROWTH_KB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    out = subprocess.run([sys.executable, "-c", code, str(z)], capture_output=True, text=True, env=env,
                         timeout=300).stdout
    assert "REFUSED" in out and "declares 600 MiB" in out, out
    assert int(out.split("GROWTH_KB")[1]) < 100 * 1024, out


# -- typed metadata ------------------------------------------------------------------------------------------------
@needs_data
@pytest.mark.parametrize("field, value, said", [
    ("poses", 5, "'poses'"), ("w", None, "'w'"), ("w", "abc", "'w'"), ("h", float("nan"), "'h'"),
    ("fps", -30.0, "'fps'"), ("K", [1, 2], "'K'"), ("dw", 10 ** 30, "'dw'"),
])
def test_record3d_metadata_fields_are_named(src, tmp_path, field, value, said):
    _, folder = _r3d_folder(src, tmp_path)
    meta = _meta(folder)
    meta[field] = value
    (folder / "metadata").write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as e:
        open_sequence(folder)
    msg = one_line(e, "metadata")
    assert f"field {said}" in msg, msg


@needs_data
def test_record3d_nan_or_repeated_timestamps_leave_the_frame_out(src, tmp_path):
    _, folder = _r3d_folder(src, tmp_path)
    meta = _meta(folder)
    meta["frameTimestamps"] = [0.0, float("nan"), 0.1, 0.1]
    (folder / "metadata").write_text(json.dumps(meta))
    seq = open_sequence(folder)
    assert len(seq) == 2 and np.all(np.isfinite(seq.timestamps))
    assert any("1.jpg: timestamp nan is not a finite number" in s for s in seq.skipped_frames)
    assert any("3.jpg" in s and "not later than" in s for s in seq.skipped_frames)


def test_every_sequence_refuses_non_finite_timestamps():
    from eligsir_o3d.core.camera import Camera

    cam = Camera(4, 4, 2.0, 2.0, 1.5, 1.5)
    for stamps in ([0.0, float("nan"), 1.0], [0.0, float("inf")]):
        with pytest.raises(DatasetError, match="finite"):
            RGBDSequence(name="x", path=Path("x"), camera=cam, depth_scale=1.0, timestamps=stamps)


def _stray(src, tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    from eligsir_o3d.datasets.phone_writers import write_stray

    return write_stray(src, tmp_path / "stray", frames=range(4))


@needs_data
def test_stray_odometry_inf_frame_and_nan_timestamp(src, tmp_path):
    out = _stray(src, tmp_path)
    odo = out / "odometry.csv"
    orig = odo.read_text()
    lines = orig.splitlines()
    keep = list(lines)
    cols = lines[1].split(",")
    header = [c.strip() for c in lines[0].split(",")]
    cols[header.index("timestamp")] = " nan"
    lines[1] = ",".join(cols)
    odo.write_text("\n".join(lines) + "\n")
    seq = open_sequence(out)
    assert len(seq) == 3 and any("timestamp nan" in s for s in seq.skipped_frames)
    cols = keep[2].split(",")
    cols[header.index("frame")] = " inf"
    keep[2] = ",".join(cols)
    odo.write_text("\n".join(keep) + "\n")
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    assert "field 'frame'" in one_line(e, "odometry.csv:3")
    from eligsir_o3d.datasets.stray import open_stray

    odo.write_text(orig)
    with pytest.raises(DatasetError, match="fps must be a positive number"):
        open_stray(out, fps=-5.0)


def _polycam(src, tmp_path):
    from eligsir_o3d.datasets.phone_writers import write_polycam

    out = write_polycam(src, tmp_path / "poly", frames=range(4))
    cams = sorted((out / "keyframes").glob("*cameras"))[0]
    return out, cams


@needs_data
@pytest.mark.parametrize("change, said", [
    (lambda d: d.update(width=None), "field 'width'"), (lambda d: d.update(fx=[1, 2]), "field 'fx'"),
    (lambda d: d.update(fx=float("nan")), "field 'fx'"), (lambda d: "a string", "expected a JSON object"),
])
def test_polycam_camera_fields_are_named(src, tmp_path, change, said):
    out, cams = _polycam(src, tmp_path)
    f = sorted(cams.glob("*.json"))[1]
    data = json.loads(f.read_text())
    new = change(data)
    f.write_text(json.dumps(data if new is None else new))
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    assert said in one_line(e, f.name)


@needs_data
def test_a_newline_in_a_file_name_is_escaped_in_the_error_line(src, tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    out, cams = _polycam(src, tmp_path)
    (cams / "9999999999\nerror: forged.json").write_text('"not a camera"')
    r = CliRunner().invoke(app, ["map", str(out), "--out", str(tmp_path / "run"), "-q", "--updates-per-frame", "1"])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert not any(line.startswith("error: forged") for line in r.output.splitlines()), r.output
    assert "\\nerror: forged" in r.output


# -- first frames follow the bad-frame rule --------------------------------------------------------------------
@needs_data
@pytest.mark.parametrize("damage", ["corrupt", "wrong-size", "loop"])
def test_stray_bad_first_depth_file_is_that_frames_fault(src, tmp_path, damage):
    out = _stray(src, tmp_path)
    good = open_sequence(out)
    first = sorted((out / "depth").glob("*.png"))[0]
    if damage == "corrupt":
        first.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    elif damage == "wrong-size":
        import cv2

        cv2.imwrite(str(first), np.ones((20, 30), np.uint16))
    else:
        first.unlink()
        first.symlink_to(first)
    seq = open_sequence(out)
    assert seq.camera == good.camera and len(seq) == len(good)
    with pytest.raises(DatasetError) as e:
        seq[0]
    msg = one_line(e, first.name)
    if damage == "loop":
        assert "loops" in msg
    seq[1]  # the next frame reads


def test_tum_list_linked_to_a_device_is_named(tmp_path):
    (tmp_path / "rgb.txt").symlink_to("/dev/zero")
    (tmp_path / "depth.txt").write_text("")
    (tmp_path / "groundtruth.txt").write_text("0 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError) as e:
        open_sequence(tmp_path)
    assert "character device" in one_line(e, "rgb.txt")


@needs_data
def test_ros2_bag_colour_encoding_not_supported_is_said(src, tmp_path):
    pytest.importorskip("rosbags")
    from eligsir_o3d.datasets.writers import write_rosbag

    out = write_rosbag(src, tmp_path / "bag", ros=2, frames=range(2), color_encoding="yuv422")
    with pytest.raises(DatasetError) as e:
        open_sequence(out)
    msg = one_line(e, "bag")
    assert "supported encoding" in msg and "yuv422" in msg and "no colour image topic found" not in msg
