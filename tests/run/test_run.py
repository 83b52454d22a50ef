"""The run as a pipeline: a results folder reproduces its run (--rerun), and an offline-reference run resumes."""

import json

import pytest

from eligsir_o3d import Config
from eligsir_o3d.run.pipeline import RunOptions, run_mapping


def _cfg():
    cfg = Config(renderer="torch")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 4
    return cfg


def test_offline_reference_resumes_from_its_checkpoint(tmp_path):
    """The resume path must rebuild the offline reference's replaced policies (it once tripped the policy check)."""
    opts = dict(max_frames=12, holdout_every=4, eval_every=0, progress=False, plots=False, offline_reference=True,
                checkpoint_every=3)
    cfg = _cfg()
    cfg.clock.offline_updates = 6
    first = run_mapping("synthetic", tmp_path, cfg, RunOptions(**opts))
    assert (tmp_path / "checkpoint.pt").is_file() and first["map_state"] == "offline-reference"
    resumed = run_mapping("synthetic", tmp_path, cfg, RunOptions(**opts, resume=True))
    assert resumed["map_state"] == "offline-reference"
    assert resumed["policies"]["fidelity"]["policy"] == first["policies"]["fidelity"]["policy"]
    assert resumed["frames_released"] < first["frames_released"]  # it continued, it did not start again


def test_rerun_reproduces_a_results_folder(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    runner = CliRunner()
    a, b = tmp_path / "a", tmp_path / "b"
    r = runner.invoke(app, ["map", "synthetic", "--max-frames", "10", "--holdout-every", "5", "--eval-every", "0",
                            "--updates-per-frame", "2", "--renderer", "torch", "--seed", "4", "--out", str(a), "-q"])
    assert r.exit_code == 0, r.output
    run = json.loads((a / "run.json").read_text())
    assert run["sequence"] == "synthetic" and run["options"]["max_frames"] == 10
    assert run["options"]["holdout_every"] == 5 and run["options"]["pose"] == "gt"
    r = runner.invoke(app, ["map", "--rerun", str(a), "--out", str(b), "-q"])
    assert r.exit_code == 0, r.output
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert json.loads((b / "config.json").read_text()) == json.loads((a / "config.json").read_text())
    assert (mb["frames_total"], mb["frames_heldout"], mb["updates"], mb["gaussians"], mb["clock"]) == \
           (ma["frames_total"], ma["frames_heldout"], ma["updates"], ma["gaussians"], "updates")
    assert mb["heldout"]["psnr"] == pytest.approx(ma["heldout"]["psnr"], abs=1e-9)


def test_rerun_of_a_folder_without_a_run_record_is_a_clear_error(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    r = CliRunner().invoke(app, ["map", "--rerun", str(tmp_path), "--out", str(tmp_path / "b")])
    assert r.exit_code == 2 and "run.json" in r.output and "Traceback" not in r.output
