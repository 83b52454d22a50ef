"""A batch never hangs and never writes over its own files: resource requests no machine can meet are refused
before the first task, a task past its time limit is stopped and reported, a sequence named like the batch's own
files gets another folder, and an ``--out`` that is a file is one line."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from typer.testing import CliRunner

from eligsir_o3d.batch.specs import BatchError, SequenceSpec, expand_inputs
from eligsir_o3d.cli.app import app
from helpers.small_runs import start_local_ray

SUN3D = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "sun3d_mit76_studyroom_f0935"


def test_a_sequence_named_like_the_batch_files_gets_its_own_folder(tmp_path):
    specs = expand_inputs([SequenceSpec(path=str(tmp_path / "summary.csv")), str(tmp_path / "Batch.json")])
    assert [s.name for s in specs] == ["summary.csv-sequence", "Batch.json-sequence"]
    with pytest.raises(BatchError, match="the batch folder's own summary.csv"):
        expand_inputs([SequenceSpec(path="synthetic", name="summary.csv", where="list.txt:1")])


def test_out_that_is_a_file_is_one_line_exit_3(tmp_path):
    f = tmp_path / "out"
    f.write_text("mine")
    r = CliRunner().invoke(app, ["batch", "synthetic", "--out", str(f), "--max-frames", "4"])
    assert r.exit_code == 3, r.output
    assert r.output.strip().splitlines() == [r.output.strip()] and "names a file, not a folder" in r.output
    assert f.read_text() == "mine"


@pytest.mark.parametrize("args, said", [(["--max-frames", "-5"], "--max-frames -5"),
                                        (["--checkpoint-every", "-3"], "--checkpoint-every -3"),
                                        (["--cpus-per-task", "0"], "--cpus-per-task 0"),
                                        (["--speed", "1e-300"], "--speed 1e-300")])
def test_batch_refuses_values_as_map_does(tmp_path, args, said):
    r = CliRunner().invoke(app, ["batch", "synthetic", "--out", str(tmp_path / "b"), *args])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert said in r.output and len(r.output.strip().splitlines()) == 1, r.output


@pytest.fixture(scope="module")
def local_ray():
    ray = start_local_ray()
    yield ray
    ray.shutdown()


def test_more_cpus_per_task_than_any_machine_is_refused_before_a_task(tmp_path, local_ray):
    r = CliRunner().invoke(app, ["batch", "synthetic", "--out", str(tmp_path / "b"), "--max-frames", "4",
                                 "--cpus-per-task", "64"])
    assert r.exit_code == 2, r.output
    assert "--cpus-per-task 64: no machine of the cluster has that many CPUs (the largest has 2)" in r.output
    assert not (tmp_path / "b" / "synthetic").exists()


def test_a_task_past_its_time_limit_is_stopped_and_reported(tmp_path, local_ray):
    from eligsir_o3d.batch import map_many

    res = map_many(["synthetic"], tmp_path / "b", max_frames=8, eval_every=0, plots=False, task_timeout=0.5,
                   echo=None)
    assert res[0].status == "failed" and "stopped after" in res[0].error and "--task-timeout" in res[0].error
    with open(tmp_path / "b" / "summary.csv") as f:
        assert [row["status"] for row in csv.DictReader(f)] == ["failed"]


@pytest.mark.skipif(not SUN3D.is_dir(), reason="../shared/data is not available")
def test_a_sequence_folder_named_summary_csv_is_mapped_and_reported(tmp_path, local_ray):
    link = tmp_path / "summary.csv"
    link.symlink_to(SUN3D.resolve())
    out = tmp_path / "b"
    r = CliRunner().invoke(app, ["batch", str(link), "--out", str(out), "--max-frames", "8", "--eval-every", "0",
                                 "--no-plots", "--updates-per-frame", "1"])
    assert r.exit_code == 0, r.output
    assert (out / "summary.csv").is_file() and (out / "summary.csv-sequence" / "metrics.json").is_file()
    with open(out / "summary.csv") as f:
        assert [row["name"] for row in csv.DictReader(f)] == ["summary.csv-sequence"]
