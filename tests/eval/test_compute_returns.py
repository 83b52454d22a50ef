"""benchmarks/quality/compute_returns.py on the synthetic room: every arm continues the run's own map over the run's
own admitted views for the CPU seconds asked, the first row is the run's map as the pipeline scored it, more
updates of an under-trained map score higher, and a folder it cannot continue is a clear error."""

import json

import pytest

from helpers.scripts import load_script, synthetic_run


def _tool():
    return load_script("benchmarks/quality/compute_returns.py")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):  # 2 updates per frame, no drain: an under-trained map
    return synthetic_run(tmp_path_factory.mktemp("returns_run"), updates_per_frame=2, drain_updates=0)


def test_arms_continue_the_runs_map(run_folder):
    tool = _tool()
    views = tool.admitted_views(run_folder)
    metrics = json.loads((run_folder / "metrics.json").read_text())
    assert len(views) == metrics["frames_admitted"]
    r = tool.evaluate(run_folder, seconds=0.4, scales=(0.25, 1.0), fused_voxel=0.05)
    rows = {row["arm"]: row for row in r["rows"]}
    assert list(rows) == ["the run's map", "scale 0.25", "scale 1", "fused 0.05 m, scale 0.25"]
    start = rows["the run's map"]
    assert start["whole"] == pytest.approx(metrics["heldout"]["psnr"], abs=1e-3)  # as the pipeline scored it
    assert start["updates"] == 0 and start["gaussians"] == metrics["gaussians"]
    for name in ("scale 0.25", "scale 1", "fused 0.05 m, scale 0.25"):
        assert rows[name]["updates"] > 0 and rows[name]["cpu_s"] >= 0.4
    assert rows["scale 0.25"]["updates"] > rows["scale 1"]["updates"]  # a coarse update is cheaper
    assert rows["scale 0.25"]["whole"] > start["whole"]  # 2 updates per frame leave the map under-trained
    fused = r["fused"]
    assert fused["frames"] == metrics["frames_source"] and fused["points"] > 100
    assert "fused map before any update" in tool.format_table(r)


def test_a_folder_without_views_is_a_clear_error(run_folder, tmp_path, capsys):
    tool = _tool()
    (tmp_path / "views_trace.csv").write_text("update,event,view\n0,refresh,\n")
    with pytest.raises(ValueError, match="no 'admit' event"):
        tool.admitted_views(tmp_path)
    with pytest.raises(ValueError, match="no views_trace.csv"):
        tool.admitted_views(tmp_path / "nowhere")
    assert tool.main([str(tmp_path), "--seconds", "0.1"]) == 2
    assert "compute_returns:" in capsys.readouterr().err
