"""Issue 31 items 6 and 7: image headers are read before decoding (a small file declaring a huge image is refused,
with bounded memory), and the cost-model calibration follows the one bad-frame rule (a truncated JPEG among the
first source frames is skipped under --on-bad-frame skip, not the end of the run)."""

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.datasets.base import DatasetError, read_color, read_depth
from eligsir_o3d.datasets.image_header import image_size

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
CAM = Camera(640, 480, 525.0, 525.0, 319.5, 239.5)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def huge_png(path: Path, w: int = 40000, h: int = 40000, rows: int = 64) -> Path:
    """A valid-looking 16-bit grey PNG that declares w x h; its IDAT holds the first ``rows`` rows of zeros."""
    raw = (b"\x00" + b"\x00" * (2 * w)) * rows
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
                     + _chunk(b"IDAT", zlib.compress(raw, 9)) + _chunk(b"IEND", b""))
    return path


def huge_jpeg(path: Path, w: int = 40000, h: int = 30000) -> Path:
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(buf.tobytes())
    k = data.index(b"\xff\xc0")
    data[k + 5:k + 9] = struct.pack(">HH", h, w)
    path.write_bytes(bytes(data))
    return path


def test_image_size_reads_png_and_jpeg_headers(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((7, 11), np.uint16))
    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((5, 13, 3), np.uint8))
    assert image_size(tmp_path / "a.png") == (11, 7) and image_size(tmp_path / "a.jpg") == (13, 5)
    assert image_size(huge_png(tmp_path / "h.png")) == (40000, 40000)
    assert image_size(huge_jpeg(tmp_path / "h.jpg")) == (40000, 30000)
    (tmp_path / "x.bin").write_bytes(b"\xff\xd8\xff")  # a cut header: unknown, the decoder says what is wrong
    assert image_size(tmp_path / "x.bin") is None


def test_a_huge_declared_image_is_refused_before_decoding(tmp_path, monkeypatch):
    import open3d as o3d

    def never(*a, **k):
        raise AssertionError("decoded before its header was checked")

    monkeypatch.setattr(o3d.t.io, "read_image", never)
    with pytest.raises(DatasetError, match=r"frame 3: depth file .*h.png declares 40000x40000 pixels.*max_image_side"):
        read_depth(huge_png(tmp_path / "h.png"), 3, CAM)
    with pytest.raises(DatasetError, match=r"declares 40000x30000"):
        read_color(huge_jpeg(tmp_path / "h.jpg"), 3, CAM)
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((100, 200), np.uint16))  # within the limit, another size
    with pytest.raises(DatasetError, match=r"is 200x100 but the intrinsics are for 640x480"):
        read_depth(tmp_path / "small.png", 4, CAM)


def test_peak_memory_stays_bounded_on_a_huge_png(tmp_path):
    p = huge_png(tmp_path / "h.png")
    code = ("import resource, sys; from pathlib import Path\n"
            "from eligsir_o3d.core.camera import Camera\nfrom eligsir_o3d.datasets.base import read_depth\n"
            "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
            "try:\n    read_depth(Path(sys.argv[1]), 0, Camera(640, 480, 525.0, 525.0, 319.5, 239.5))\n"
            "except ValueError as e:\n    print('refused', e)\n"
            "print('grew_kib', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base)\n")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, env=env, timeout=300)
    assert "refused" in r.stdout and "declares 40000x40000" in r.stdout, r.stdout + r.stderr
    grew = int(r.stdout.split("grew_kib")[1].split()[0])
    assert grew < 64 * 1024, f"peak RSS grew {grew} KiB reading a header"


@pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")
@pytest.mark.parametrize("rule", ["skip", "stop"])
def test_the_cost_model_calibration_follows_the_bad_frame_rule(tmp_path, rule, caplog):
    from eligsir_o3d import Config
    from eligsir_o3d.budget import CostModel
    from eligsir_o3d.run.cost_source import run_cost_model
    from eligsir_o3d.run.pipeline import CALIBRATION_FRAMES, MappingPipeline, RunOptions
    from tests.run.test_heldout_faults import kitchen_copy

    root = kitchen_copy(tmp_path / "kitchen", 24)
    bad = root / "rgb" / "000001.jpg"  # a source frame among the first CALIBRATION_FRAMES
    data = bad.read_bytes()
    bad.unlink()
    bad.write_bytes(data[:500])
    cfg = Config(renderer="torch")
    cfg.clock.cost_source, cfg.clock.on_bad_frame = "calibrate", rule
    p = MappingPipeline(str(root), tmp_path / "out", cfg, RunOptions(max_frames=24, progress=False, holdout_every=8))
    p.open()
    timed = []
    p.rec = SimpleNamespace(config=p.config, calibrate=lambda frames, n_frames: (timed.extend(f.index for f in frames)
                                                                 or (CostModel(), {"cache": "test"})))
    if rule == "stop":
        with pytest.raises(DatasetError, match="frame 1: colour file .*000001.jpg is truncated"):
            run_cost_model(p.rec, p.seq, p.source, p.path, offline=False)
        return
    run_cost_model(p.rec, p.seq, p.source, p.path, offline=False)
    assert 1 not in timed and len(timed) == CALIBRATION_FRAMES and timed[0] == 0
    assert "cost-model calibration: not timing frame 1: colour file" in caplog.text
