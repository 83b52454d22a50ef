"""Live mapping through the frame-source seam, without a camera: a RealSense bag replayed by Open3D's reader."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eligsir_o3d.datasets import open_sequence

pytest.importorskip("rosbags")
from eligsir_o3d.datasets.writers import write_realsense_bag  # noqa: E402
from eligsir_o3d.run.live_run import SequenceReplay, run_live  # noqa: E402

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


def _cfg():
    from eligsir_o3d import Config

    cfg = Config(renderer="cpu")
    cfg.clock.drain_updates = 5
    return cfg


def test_cli_live_replays_a_realsense_bag_in_real_time(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    seq = open_sequence(SEVEN)  # frames on the colour camera (f 525), depth registered into it
    bag = write_realsense_bag(seq, tmp_path / "cap.bag", frames=range(12))
    r = CliRunner().invoke(app, ["live", "--replay", str(bag), "--out", str(tmp_path / "live")])
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "live" / "live.json").read_text())
    assert s["source"] == "realsense-bag" and s["captured"] >= 1
    assert s["integrated"] + s["dropped"] + s["lost"] + s["bad"] == s["captured"]
    assert s["camera"]["fx"] == seq.camera.fx == 525.0 and s["gaussians"] > 0
    assert (tmp_path / "live" / "map.ply").is_file()
    traj = [ln for ln in (tmp_path / "live" / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(traj) == s["integrated"]


def test_unpaced_stream_overflows_the_queue_and_drops_oldest(tmp_path):
    seq = open_sequence(SEVEN)
    s = run_live(SequenceReplay(seq, paced=False, max_frames=10), tmp_path / "flood", _cfg(), queue_size=2,
                 drain_s=0.2)
    assert s["captured"] == 10 and s["dropped"] > 0  # frames arrive faster than tracking + mapping
    assert s["integrated"] + s["dropped"] + s["lost"] + s["bad"] == 10


def test_live_without_a_camera_is_a_one_line_error(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    r = CliRunner().invoke(app, ["live", "--replay", str(tmp_path / "missing.bag"), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "Traceback" not in r.output and "missing.bag" in r.output, r.output
