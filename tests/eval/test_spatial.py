"""eval.spatial: the per-cell delta map of two runs (paper Fig. "Spatial effect of Map-Guided View Scheduling")."""

import json

import pytest

from eligsir_o3d.eval.spatial import cell_deltas, compare_spatial, format_summary


def _table(keys, q, eligible=None, measurable=None, size=0.5):
    n = len(keys)
    return {"cell_size": size, "up_axis": 2, "quality_threshold": 20.0, "keys": keys, "q": q,
            "eligible": eligible or [True] * n, "measurable": measurable or [True] * n}


# 12 cells of run B (the ablation); run A differs per cell by a known delta
KEYS = [[i % 4, i // 4, 0] for i in range(12)]
Q_B = [8.0, 12.0, 14.0, 16.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.0]
DELTA = [11.0, 6.0, -1.0, 0.5, 2.0, 0.0, -6.0, 1.0, 1.0, 1.0, 1.0, 1.0]
Q_A = [b + d for b, d in zip(Q_B, DELTA)]


def test_counts_and_deciles():
    r = cell_deltas(_table(KEYS, Q_A), _table(KEYS, Q_B))
    s = r["summary"]
    assert r["n_common"] == 12
    assert s["improved_10db"] == 1 and s["improved_5db"] == 2
    assert s["worse"] == 2 and s["worse_5db"] == 1
    assert s["decile_cells"] == 2  # ceil(10 % of 12)
    assert s["weak_b_under_b"] == pytest.approx((8 + 12) / 2)
    assert s["weak_b_under_a"] == pytest.approx((19 + 18) / 2)
    # A's own two lowest cells: 13 (14 - 1) and 14 (20 - 6)
    assert s["own_decile_a"] == pytest.approx((13 + 14) / 2)
    assert s["mean_delta"] == pytest.approx(sum(DELTA) / 12)
    assert s["max_delta"] == 11.0 and s["min_delta"] == -6.0


def test_only_cells_evaluable_in_both_count():
    elig = [True] * 12
    elig[0] = False  # B's weakest cell is not evaluable in A: it leaves the comparison
    q_b = list(Q_B)
    q_b[11] = None  # no render value in B
    r = cell_deltas(_table(KEYS, Q_A, eligible=elig), _table(KEYS + [[9, 9, 9]], q_b + [5.0]))
    assert r["n_common"] == 10 and r["n_only_a"] == 1 and r["n_only_b"] == 2
    assert r["summary"]["improved_10db"] == 0
    assert [0, 0, 0] not in r["keys"]


def test_cell_size_mismatch_is_an_error():
    with pytest.raises(ValueError, match="cell sizes differ"):
        cell_deltas(_table(KEYS, Q_A), _table(KEYS, Q_B, size=0.25))


def _folder(path, q, dataset="seq", total=100):
    path.mkdir()
    (path / "metrics.json").write_text(json.dumps({"dataset": dataset, "frames_total": total, "frames_heldout": 12}))
    (path / "cells.json").write_text(json.dumps(_table(KEYS, q)))
    return path


def test_compare_folders_writes_json_and_png(tmp_path):
    a, b = _folder(tmp_path / "full", Q_A), _folder(tmp_path / "abl", Q_B)
    r = compare_spatial(a, b, tmp_path / "out")
    assert (tmp_path / "out" / "spatial_delta.png").stat().st_size > 0
    saved = json.loads((tmp_path / "out" / "spatial_delta.json").read_text())
    assert saved["summary"]["improved_10db"] == 1 and saved["delta"][0] == 11.0
    assert "> 10 dB: 1" in format_summary(r)


def test_compare_folders_of_different_sequences_fails(tmp_path):
    a, b = _folder(tmp_path / "a", Q_A), _folder(tmp_path / "b", Q_B, dataset="other")
    with pytest.raises(ValueError, match="same sequence"):
        compare_spatial(a, b)


def test_cli_eval_of_two_folders_writes_the_delta_map(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli import app

    a, b = _folder(tmp_path / "full", Q_A), _folder(tmp_path / "abl", Q_B)
    res = CliRunner().invoke(app, ["eval", str(a), str(b), "--spatial-out", str(tmp_path / "fig")])
    assert res.exit_code == 0, res.output
    assert "> 10 dB: 1" in res.output
    assert (tmp_path / "fig" / "spatial_delta.png").is_file()


def test_spread_over_seeds():
    from eligsir_o3d.eval.spatial import spread

    r1 = cell_deltas(_table(KEYS, Q_A), _table(KEYS, Q_B))
    r2 = cell_deltas(_table(KEYS, Q_B), _table(KEYS, Q_B))  # identical runs: nothing improved
    s = spread([r1, r2])
    assert s["improved_10db"] == (0.5, pytest.approx(0.5 ** 0.5))
    assert s["n_common"] == (12.0, 0.0)
    assert spread([r1])["worse"] == (2.0, None)


def test_spatial_table_and_criteria(tmp_path):
    from eligsir_o3d.eval.spatial import format_spatial, spatial_table, view_criteria

    a, b = _folder(tmp_path / "full", Q_A), _folder(tmp_path / "abl", Q_B)
    table = spatial_table({"scheduling": [(a, b, tmp_path / "sp")], "growth": [(a, tmp_path / "missing", tmp_path)]})
    assert list(table) == ["scheduling"] and (tmp_path / "sp" / "spatial_delta.png").is_file()
    text = format_spatial(table, {"scheduling": "w/o view scheduling"})
    assert "| w/o view scheduling | 12 |" in text and "| 1.0 |" in text  # one cell > +10 dB
    full = {"psnr": 20.0, "psnr_sd": 0.3, "cuc20": 60.0, "cuc20_sd": 1.0}
    abl = {"psnr": 20.2, "psnr_sd": 0.1, "cuc20": 62.0, "cuc20_sd": 0.5}
    lines = view_criteria(full, abl, table["scheduling"]["spread"])
    assert lines[0].startswith("full's held-out PSNR") and ": yes (margin -0.20, sd 0.30)" in lines[0]
    assert ": NO (margin -2.00, sd 1.00)" in lines[1]
    assert "weakest decile of cells higher than w/o view scheduling's: yes (13.50 vs 10.00 dB" in lines[2]
    assert lines[3].startswith("cells improved by more than 10 dB: 1.0 per seed")
