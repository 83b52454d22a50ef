"""Issue 31 items 10 and 11 (--holdout-every): a recording shorter than the held-out period, or --holdout-every 0,
is mapped with every frame and reported as having no held-out figure; a negative period is one line, exit 2."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.app import app

MICRO = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "replica_office0_micro4"
FAST = ["--updates-per-frame", "1", "--set", "clock.drain_updates=2", "--eval-every", "0", "--renderer", "torch",
        "--no-pictures", "-q"]


@pytest.mark.parametrize("extra", [["--max-frames", "3"], ["--max-frames", "6", "--holdout-every", "0"]])
def test_no_held_out_frame_maps_and_says_so(tmp_path, extra):
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), *extra, *FAST])
    assert r.exit_code == 0 and "Traceback" not in r.output, r.output
    assert "held-out PSNR n/a" in r.output and "HeldoutEvaluator" not in r.output
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["heldout"]["psnr"] is None and m["frames_heldout"] == 0 and m["gaussians"] > 0


def test_a_negative_holdout_period_is_one_line(tmp_path):
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), "--holdout-every", "-2", *FAST])
    assert r.exit_code == 2 and "--holdout-every -2: must be an integer >= 0" in r.output, r.output
    assert "Traceback" not in r.output


@pytest.mark.skipif(not MICRO.is_dir(), reason="../shared/data is not available")
def test_the_four_frame_replica_micro_recording_maps(tmp_path):
    r = CliRunner().invoke(app, ["map", str(MICRO), "--out", str(tmp_path / "o"), *FAST,
                                 "--set", "clock.drain_updates=0"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["frames_source"] == 4
