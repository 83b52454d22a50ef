"""eligsir ablate (Table III): the table, its per-seed means, the CUC@20 cell counts and the paper's criteria, read
back from results folders (--table-only); eligsir map's options and defaults; a short real run of two variants."""

import inspect
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from eligsir_o3d.cli.ablate_cmd import ablate_cmd
from eligsir_o3d.cli.app import app


class _Cli:
    """``main([...])`` runs ``eligsir ablate ...`` and returns its exit status; its output is printed (capsys)."""

    @staticmethod
    def main(argv) -> int:
        r = CliRunner().invoke(app, ["ablate", *argv])
        print(r.output)
        if r.exit_code == 2 and "error:" in r.output:
            raise SystemExit(r.output)
        return r.exit_code


@pytest.fixture(scope="module")
def ablation():
    return _Cli()


def _write(run: Path, psnr, auc, cuc_cells, n_cells, mpix):
    run.mkdir(parents=True)
    qs = [25.0] * cuc_cells + [15.0] * (n_cells - cuc_cells) + [30.0]  # the last cell is not evaluable
    cells = {"q": qs, "eligible": [True] * n_cells + [False], "measurable": [True] * (n_cells + 1)}
    (run / "cells.json").write_text(json.dumps(cells))
    m = {"heldout": {"psnr": psnr}, "cvq_auc": auc, "cuc20_final": cuc_cells / n_cells, "supervised_mpix": mpix,
         "gaussians": 5000, "updates": 100, "curve": [{"progress": 0.1, "cvq": auc}, {"progress": 1.0, "cvq": auc}]}
    (run / "metrics.json").write_text(json.dumps(m))


def test_the_options_are_eligsir_maps():
    """Every option of eligsir map that makes sense for several runs, with the same default; speed: the config's,
    the recorded rate (the paper's online ablations run at acquisition speed)."""
    from eligsir_o3d import Config
    from eligsir_o3d.cli.app import map_cmd

    mine, theirs = inspect.signature(ablate_cmd).parameters, inspect.signature(map_cmd).parameters
    shared = set(mine) & set(theirs)
    assert set(theirs) - shared == {"ablate", "rerun", "resume", "checkpoint_every", "force_unlock", "view",
                                    "view_port", "view_host"}
    assert set(mine) - shared == {"variants", "seeds", "table_only"}
    for name in shared:
        assert mine[name].default is theirs[name].default, name
    assert Config().clock.speed == 1.0


def test_seed_means_cell_counts_and_criteria(ablation, tmp_path, capsys):
    # full: seeds 20.0 / 21.0 (mean 20.5), 30 + 32 of 40 cells; fixed resolution: 20.8 dB, 4x the pixels
    _write(tmp_path / "full-s0", 20.0, 19.0, 30, 40, 10.0)
    _write(tmp_path / "full-s1", 21.0, 19.4, 32, 40, 10.0)
    _write(tmp_path / "fidelity-s0", 20.8, 19.1, 31, 40, 40.0)
    _write(tmp_path / "fidelity-s1", 20.8, 19.1, 31, 40, 40.0)
    rc = ablation.main(["--out", str(tmp_path), "--table-only", "--seeds", "0,1", "--variants", "full,fidelity"])
    assert rc == 0
    rows = json.loads((tmp_path / "table.json").read_text())["rows"]
    assert rows["full"]["psnr"] == pytest.approx(20.5) and rows["full"]["psnr_sd"] == pytest.approx(0.7071, abs=1e-3)
    assert rows["full"]["cells"] == "62/80" and rows["fidelity"]["cells"] == "62/80"
    assert rows["full"]["cuc20"] == pytest.approx(77.5)
    out = capsys.readouterr().out
    assert "full has the best held-out PSNR: NO (20.50 vs w/o adaptive fidelity 20.80" in out
    assert "full has the best CUC@20: yes" in out
    assert "4.00x fewer pixels than fixed native resolution (>= 3: yes) at CVQ-AUC 19.20 vs 19.10 (no lower: yes)" in out
    assert "| full s1 | 21.00 |" in out  # one row per run below the means


def test_single_runs_keep_the_variant_folders(ablation, tmp_path, capsys):
    _write(tmp_path / "full", 21.0, 19.0, 10, 20, 5.0)
    assert ablation.main(["--out", str(tmp_path), "--table-only", "--variants", "full"]) == 0
    row = json.loads((tmp_path / "table.json").read_text())["rows"]["full"]
    assert row["psnr"] == 21.0 and row["cells"] == "10/20" and "psnr_sd" not in row


def test_bad_seeds_are_named(ablation, tmp_path):
    with pytest.raises(SystemExit, match="--seeds"):
        ablation.main(["--out", str(tmp_path), "--table-only", "--seeds", "0,x"])
    with pytest.raises(SystemExit, match="unknown variant"):
        ablation.main(["--out", str(tmp_path), "--table-only", "--variants", "full,scheduling"])


def test_the_fidelity_trace_figure_is_drawn_beside_the_fixed_resolution_curve(ablation, tmp_path, capsys):
    """Fig. 6 (eligsir_o3d.eval.plots.fidelity_trace_plot): the full run's fidelity_trace.csv, the fixed-resolution
    run's supervised pixels from its curve; a PNG of 7 x 6.5 inches at 120 dpi."""
    from eligsir_o3d.run.results import write_side_files

    _write(tmp_path / "full", 21.0, 19.0, 10, 20, 5.0)
    _write(tmp_path / "fidelity", 20.0, 18.0, 8, 20, 20.0)
    fixed = json.loads((tmp_path / "fidelity" / "metrics.json").read_text())
    fixed["curve"] = [{"progress": p, "cvq": 18.0, "updates": 5 * k, "supervised_mpix": 2.0 * k}
                      for k, p in enumerate((0.1, 0.5, 1.0), 1)]
    (tmp_path / "fidelity" / "metrics.json").write_text(json.dumps(fixed))
    trace = [{"update": u, "backlog": u % 3, "backlog_ema": 1.0, "scale": 0.25 if u < 5 else 1.0,
              "supervised_mpix": 0.1 * u} for u in range(10)]
    write_side_files(tmp_path / "full", None, trace)
    assert ablation.main(["--out", str(tmp_path), "--table-only", "--variants", "full,fidelity"]) == 0
    png = (tmp_path / "fidelity_trace.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")) == (840, 780)
    assert f"fidelity trace: {tmp_path / 'fidelity_trace.png'}" in capsys.readouterr().out


def test_a_short_run_of_two_variants(tmp_path):
    """Each variant is an eligsir map run with the shared options; the ablated one records its ablation."""
    out = tmp_path / "abl"
    r = CliRunner().invoke(app, ["ablate", "synthetic", "--max-frames", "6", "--clock", "updates",
                                 "--updates-per-frame", "2", "--eval-every", "0", "--holdout-every", "3",
                                 "--no-pictures", "--variants", "full,growth", "--out", str(out), "-q"])
    assert r.exit_code == 0, r.output
    ablate = {v: json.loads((out / v / "config.json").read_text())["ablate"] for v in ("full", "growth")}
    assert ablate == {"full": [], "growth": ["growth"]}
    rows = json.loads((out / "table.json").read_text())["rows"]
    assert set(rows) == {"full", "growth"} and rows["full"]["updates"] > 0
    assert "| EliGSiR |" in r.output and "| w/o targeted growth |" in r.output
