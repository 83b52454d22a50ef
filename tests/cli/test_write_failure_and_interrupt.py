"""Issue 31 item 11 (smaller items): a results folder that cannot be written is exit 3 (a write failure, as the
README says), and Ctrl-C during eligsir map ends with one line saying how to go on."""

import os

from typer.testing import CliRunner

from eligsir_o3d.cli.app import app
from eligsir_o3d.run.pipeline import MappingPipeline

FAST = ["--max-frames", "6", "--updates-per-frame", "1", "--eval-every", "0", "--renderer", "torch",
        "--no-pictures", "-q"]


def test_a_read_only_out_is_exit_3(tmp_path, monkeypatch):
    out = tmp_path / "ro"
    out.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **k: False if str(p) == str(out) and mode & os.W_OK else real(p, mode, **k))
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(out), *FAST])
    assert r.exit_code == 3 and "cannot write" in r.output and "Permission denied" in r.output, r.output
    assert "Traceback" not in r.output


def test_ctrl_c_says_how_to_go_on(tmp_path, monkeypatch):
    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(MappingPipeline, "stream", interrupted)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o"), *FAST])
    assert r.exit_code == 130 and "interrupted;" in r.output and "--overwrite" in r.output, r.output
    (tmp_path / "o2").mkdir()
    (tmp_path / "o2" / "checkpoint.pt").write_bytes(b"")
    monkeypatch.setattr("eligsir_o3d.run.pipeline.MappingPipeline.run", interrupted)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(tmp_path / "o2"), *FAST])
    assert r.exit_code == 130 and "--resume" in r.output, r.output
