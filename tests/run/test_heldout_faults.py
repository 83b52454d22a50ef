"""A held-out frame that cannot be read is dropped from the evaluation split and reported, like a bad source frame
is skipped and reported (issue 14 item 1): a 60-frame copy of the 7-Scenes kitchen with a missing held-out depth
file and a truncated source JPEG maps to the end and lists both in metrics.json; with --on-bad-frame stop the run
ends with one line naming the first. And the same at the library level, an invalid held-out pose included."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d.datasets import DatasetError, open_sequence
from eligsir_o3d.core.frame import FrameError
from eligsir_o3d.run.frame_faults import read_heldout

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")


def kitchen_copy(root: Path, n: int) -> Path:
    """The first ``n`` frames of the kitchen: its text files cut to ``n`` entries, its images linked (a test that
    damages one must replace the link by a file, never write through it)."""
    root.mkdir(parents=True)
    for item in SEVEN.iterdir():
        if item.is_dir():
            (root / item.name).mkdir()
            for f in sorted(item.iterdir())[:n]:
                os.symlink(f.resolve(), root / item.name / f.name)
        elif item.name in LISTS:
            lines = item.read_text().splitlines()
            head = [ln for ln in lines if ln.startswith("#")]
            rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")][:n]
            (root / item.name).write_text("\n".join(head + rows) + "\n")
        else:
            shutil.copy(item, root / item.name)
    return root


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.unlink()  # the link, not the shared file
    path.write_bytes(data[: int(len(data) * keep)])


@pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")
def test_bad_heldout_and_source_frames_are_reported_and_the_run_completes(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    root = kitchen_copy(tmp_path / "kitchen", 60)
    (root / "depth" / "000012.png").unlink()  # held out: 12 % 8 == 4
    _truncate(root / "rgb" / "000030.jpg")  # a source frame, cut in half (libjpeg alone decodes it, grey)
    common = [str(root), "--max-frames", "60", "--updates-per-frame", "1", "--eval-every", "0", "--no-pictures",
              "--set", "clock.drain_updates=0", "-q"]
    runner = CliRunner()
    r = runner.invoke(app, ["map", *common, "--out", str(tmp_path / "skip")])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "skip" / "metrics.json").read_text())
    assert m["heldout_skipped"] == [{"index": 12, "file": str(root / "depth" / "000012.png"),
                                     "reason": f"depth file {root / 'depth' / '000012.png'} does not exist"}]
    assert len(m["skipped_frames"]) == 1, m["skipped_frames"]
    assert m["skipped_frames"][0].startswith("frame 30: colour file") and "000030.jpg is truncated" in \
        m["skipped_frames"][0]
    # the evaluation ran on the 6 held-out frames that can be read; the split is unchanged (12 is not mapped)
    assert [v["index"] for v in m["per_view"]] == [4, 20, 28, 36, 44, 52]
    assert m["frames_heldout"] == 7 and m["frames_source"] == 53 and m["heldout"]["psnr"] is not None
    assert len([ln for ln in (tmp_path / "skip" / "trajectory.txt").read_text().splitlines()
                if not ln.startswith("#")]) == 52  # 53 source frames, the truncated one skipped

    r = runner.invoke(app, ["map", *common, "--out", str(tmp_path / "stop"), "--on-bad-frame", "stop"])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: frame 12: depth file") and \
        lines[0].endswith("000012.png does not exist"), r.output
    assert not (tmp_path / "stop" / "metrics.json").exists()


def _write_room(root: Path, n: int = 10) -> None:
    from tests.core.test_bad_input import _write_folder

    _write_folder(root, n)


def test_read_heldout_drops_unreadable_frames_and_invalid_poses(tmp_path, caplog):
    root = tmp_path / "room"
    _write_room(root)
    (root / "color" / "000001.png").write_bytes(b"\x89PNG cut")
    seq = open_sequence(root)
    seq.poses[5] = np.full((4, 4), np.nan)  # a reader that hands out an invalid pose for a held-out frame
    frames, skipped = read_heldout(seq, [1, 5, 9], depth_max=8.0)
    assert [f.index for f in frames] == [9]
    assert skipped[0] == {"index": 1, "file": str(root / "color" / "000001.png"),
                          "reason": f"colour file {root / 'color' / '000001.png'} is corrupt or not an image"}
    assert skipped[1]["index"] == 5 and skipped[1]["file"] == str(root) and "pose" in skipped[1]["reason"] \
        and "NaN" in skipped[1]["reason"], skipped[1]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("held-out frame dropped" in w and "000001.png is corrupt" in w for w in warned), warned
    with pytest.raises(DatasetError, match=r"^frame 1: colour file .*000001\.png is corrupt"):
        read_heldout(seq, [1, 5, 9], depth_max=8.0, on_bad_frame="stop")
    with pytest.raises(FrameError, match=r"^frame 5: pose"):
        read_heldout(seq, [5, 9], depth_max=8.0, on_bad_frame="stop")
    with pytest.raises(ValueError, match=r"none of the 2 held-out frames can be read \(the first: frame 1: colour"):
        read_heldout(seq, [1, 5], depth_max=8.0)
