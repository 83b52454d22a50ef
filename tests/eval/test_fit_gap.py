"""benchmarks/quality/fit_gap.py on the synthetic room: the run's map scored on its training views, its other source
frames and its held-out views (the held-out row as the pipeline scored it), and continued over one or all of its
views; a single view is fitted fast; a folder it cannot read is a clear error."""

import json

import numpy as np
import pytest

from helpers.scripts import load_script, synthetic_run


def _tool():
    return load_script("benchmarks/quality/fit_gap.py")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):  # 2 updates per frame, no drain: an under-trained map
    return synthetic_run(tmp_path_factory.mktemp("fit_gap_run"), updates_per_frame=2, drain_updates=0)


def test_rows_and_continuations(run_folder):
    tool = _tool()
    metrics = json.loads((run_folder / "metrics.json").read_text())
    r = tool.evaluate(run_folder, updates=30, view_counts=(1, 0), stride=1)
    rows = {row["frames"]: row for row in r["rows"]}
    assert rows["admitted views"]["n"] == metrics["frames_admitted"] == r["views"]
    assert rows["held-out views"]["n"] == metrics["frames_heldout"]
    assert rows["held-out views"]["full"] == pytest.approx(metrics["heldout"]["psnr"], abs=1e-3)
    assert r["scale"] in (0.25, 0.5, 1.0) and r["gaussians"] == metrics["gaussians"]
    one, every = r["fits"]
    assert one["views"] == 1 and every["views"] == r["views"]
    assert one["updates"] == every["updates"] == 30
    assert one["after"]["scaled"] > one["before"]["scaled"] + 1.0  # one view alone is fitted fast
    assert every["before"]["scaled"] == pytest.approx(rows["admitted views"]["scaled"], abs=1e-6)
    table = tool.format_table(r)
    assert "held-out views" in table and "K = 1" in table


def test_area_average_and_even_choice():
    tool = _tool()
    img = np.arange(2 * 6 * 3, dtype=np.float32).reshape(2, 6, 3)
    avg = tool.area_average(img, 2)
    assert avg.shape == (1, 3, 3)
    assert np.allclose(avg[0, 0], img[:2, :2].reshape(-1, 3).mean(0))
    assert tool.area_average(img, 1) is img
    items = list(range(10))
    assert tool.evenly(items, 0) == items and tool.evenly(items, 12) == items
    assert tool.evenly(items, 1) == [5] and tool.evenly(items, 3) == [0, 4, 9]


def test_a_folder_it_cannot_read_is_a_clear_error(tmp_path, capsys):
    tool = _tool()
    assert tool.main([str(tmp_path / "nowhere"), "--updates", "1"]) == 2
    assert "fit_gap:" in capsys.readouterr().err
