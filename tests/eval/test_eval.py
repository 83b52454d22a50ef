"""Evaluation protocol (paper, "Evaluation Protocol"): formulas checked on hand-made frames with planar depth.

Scene: a wall at z = 1.25 m seen by cameras looking along +z. With a 20x20 image and f = 100 px the wall patch
spans 0.24 m, so a camera at x = y = 0.25 m sees only cell (0, 0, 2) and one at x = 0.5 m splits its image between
cells (0, 0, 2) (columns 0-9) and (1, 0, 2) (columns 10-19): every sample's cell is known.
"""

import json
import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.eval import (PSNR_CAP, HeldoutEvaluator, RegionalQuality, compare_results, cvq_auc, depth_rmse,
                              lpips_or_none, psnr, ssim, write_plots)
from eligsir_o3d.core.frame import Frame

W = H = 20
CAM = Camera(W, H, 100.0, 100.0, (W - 1) / 2, (H - 1) / 2)
WALL_Z = 1.25


def make_frame(index, x=0.25, y=0.25, n_valid=None, color=0.5):
    """A frame at (x, y, 0) looking at the wall; ``n_valid`` keeps only the first n pixels (row-major) valid."""
    depth = np.full((H, W), WALL_Z, np.float32)
    if n_valid is not None:
        depth.reshape(-1)[n_valid:] = 0.0
    rgb = np.full((H, W, 3), color, np.float32)
    T = np.eye(4)
    T[:3, 3] = (x, y, 0.0)
    return Frame.from_arrays(rgb, depth, CAM, T, index=index, timestamp=index / 30.0)


def render_from(color_fn):
    """render_fn whose colour is color_fn(frame) (None -> missing render); depth is the reference depth."""
    def render(frame):
        c = color_fn(frame)
        return None if c is None else SimpleNamespace(color=c, depth=frame.depth.clone())
    return render


perfect = render_from(lambda f: f.color.clone())


def offset(delta):
    return render_from(lambda f: f.color + delta)


def evaluator(frames, **kw):
    kw.setdefault("sample_stride", 1)
    return HeldoutEvaluator(frames, **kw)


def eligible_run(ev, sources):
    for s in sources:
        ev.observe_source(s)


# --- image metrics -----------------------------------------------------------------------------------------------
def test_perfect_render_gives_capped_psnr():
    ref = torch.rand(H, W, 3)
    assert psnr(ref, ref) == pytest.approx(PSNR_CAP) == pytest.approx(120.0)
    assert ssim(ref, ref) == pytest.approx(1.0, abs=1e-6)


def test_known_mse_gives_known_psnr():
    ref = torch.full((H, W, 3), 0.5)
    assert psnr(ref + 0.125, ref) == pytest.approx(-10 * math.log10(0.125 ** 2), abs=1e-9)  # 18.06 dB
    assert psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-4)
    pred = ref.clone()
    pred[:, :10] += 0.25  # only the left half is wrong
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[:, 10:] = True
    assert psnr(pred, ref, mask) == pytest.approx(PSNR_CAP)
    assert psnr(pred, ref) == pytest.approx(-10 * math.log10(0.25 ** 2 / 2), abs=1e-9)
    assert psnr(pred.numpy(), ref.numpy()) == psnr(pred, ref)  # numpy arrays work too
    assert psnr(torch.full((H, W, 3), 2.0), torch.ones(H, W, 3)) == pytest.approx(PSNR_CAP)  # clamped to [0, 1]


def test_non_finite_colour_is_a_failure():
    ref = torch.full((H, W, 3), 0.5)
    pred = ref.clone()
    pred[0, 0, 0] = float("nan")
    assert psnr(pred, ref) == pytest.approx(-10 * math.log10(1.0 / (H * W * 3)))


def test_lpips_never_downloads(monkeypatch):
    def no_download(*a, **k):
        raise AssertionError("LPIPS tried to download")
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_download)
    monkeypatch.setattr(torch.hub, "download_url_to_file", no_download)
    v = lpips_or_none(torch.rand(32, 32, 3), torch.rand(32, 32, 3))
    assert v is None or (0.0 <= v < 2.0)


def test_depth_rmse_masking_policy():
    ref = torch.full((4, 4), 2.0)
    ref[0, :] = 0.0  # no reference measurement: not scored
    ref[1, :] = 3.0
    pred = ref.clone()
    assert depth_rmse(pred, ref) == 0.0
    pred[2, 0] = 0.0  # missing render pixel: error = full reference depth (2 m)
    assert depth_rmse(pred, ref) == pytest.approx(math.sqrt(4.0 / 12))
    pred[2, 1] = float("nan")  # non-finite render = missing as well
    assert depth_rmse(pred, ref) == pytest.approx(math.sqrt(8.0 / 12))
    pred[1, 0] = 4.0  # 1 m off at 3 m reference depth: only in the unrestricted RMSE
    assert depth_rmse(pred, ref, max_depth=2.0) == pytest.approx(math.sqrt(8.0 / 8))
    assert depth_rmse(None, ref) == pytest.approx(math.sqrt((4 * 9 + 8 * 4) / 12))
    assert math.isnan(depth_rmse(pred, torch.zeros(4, 4)))


# --- regional quality --------------------------------------------------------------------------------------------
def test_cells_live_on_an_open3d_hashmap():
    ev = evaluator([make_frame(0, x=0.5), make_frame(1, x=0.5)])
    reg = ev.regional
    assert isinstance(reg, RegionalQuality)
    assert sorted(map(tuple, reg.keys.tolist())) == [(0, 0, 2), (1, 0, 2)]
    ids = reg.cell_ids(torch.tensor([[1, 0, 2], [5, 5, 5], [0, 0, 2]], dtype=torch.int32))
    assert ids[1] == -1 and sorted(ids[[0, 2]].tolist()) == [0, 1]
    assert reg.keys[ids[0]].tolist() == [1, 0, 2]
    assert reg.n_samples.tolist() == [400, 400] and reg.n_views.tolist() == [2, 2]


def test_key_dedup_matches_torch_unique():
    from eligsir_o3d.eval.regional import unique_keys
    keys = torch.randint(-40, 40, (5000, 3), dtype=torch.int32)
    keys[:3] = torch.tensor([[-(1 << 19), 0, 5], [(1 << 19), -1, -1], [0, 0, 0]], dtype=torch.int32)
    uniq, inv = unique_keys(keys)
    ref = torch.unique(keys, dim=0)
    assert torch.equal(uniq, ref) and torch.equal(uniq[inv], keys)


def test_measurable_needs_300_samples_from_two_heldout_views():
    ev = evaluator([make_frame(0, n_valid=150), make_frame(1, n_valid=149)])
    assert ev.regional.n_samples.tolist() == [299] and not ev.regional.measurable.any()
    ev = evaluator([make_frame(0, n_valid=150), make_frame(1, n_valid=150)])
    assert ev.regional.n_samples.tolist() == [300] and ev.regional.measurable.all()
    ev = evaluator([make_frame(0, n_valid=400)])  # 400 samples, but one view
    assert not ev.regional.measurable.any()
    ev = evaluator([make_frame(0, n_valid=150), make_frame(1, n_valid=150)], sample_stride=2)
    assert not ev.regional.measurable.any()  # |Omega_c| counts subsampled pixels


def test_eligibility_needs_two_distinct_source_views_and_ignores_heldout():
    held = [make_frame(0), make_frame(1)]
    ev = evaluator(held)
    kw = dict(t_s=0.0, updates=0, supervised_mpix=0.0, gaussians=0)
    ev.observe_source(make_frame(5))
    ev.observe_source(make_frame(5))  # the same view again
    assert ev.observe_source(held[0]) is False and ev.observe_source(held[1]) is False  # held-out: never counts
    rec = ev.checkpoint(perfect, progress=0.5, **kw)
    assert rec["n_eligible"] == 0 and rec["n_measurable"] == 1 and rec["n_evaluable"] == 0
    assert rec["cvq"] is None and rec["cuc20"] is None
    ev.observe_source(make_frame(7, x=5.0))  # a distinct view that sees another place: no help
    assert ev.checkpoint(perfect, progress=0.6, **kw)["n_eligible"] == 0
    ev.observe_source(make_frame(6))  # second distinct source view of the cell
    assert ev.regional.t_vis.tolist() == [-1]  # eligible only from the next checkpoint on
    rec = ev.checkpoint(perfect, progress=0.7, **kw)
    assert rec["n_eligible"] == 1 and rec["n_evaluable"] == 1 and ev.regional.t_vis.tolist() == [2]
    assert rec["cvq"] == pytest.approx(PSNR_CAP) and rec["cuc20"] == 1.0


def two_cell_evaluator(**kw):
    ev = evaluator([make_frame(0, x=0.5), make_frame(1, x=0.5)], **kw)
    eligible_run(ev, [make_frame(10, x=0.5), make_frame(11, x=0.5)])
    return ev


def split_render(left, right):
    """Colour error `left` on image columns 0-9 (cell (0,0,2)) and `right` on columns 10-19 (cell (1,0,2))."""
    def color(f):
        c = f.color.clone()
        c[:, :10] += left
        c[:, 10:] += right
        return c
    return render_from(color)


def test_cell_psnr_cvq_and_cuc_thresholds():
    ev = two_cell_evaluator()
    rec = ev.checkpoint(split_render(0.0625, 0.125), t_s=1.0, progress=1.0, updates=100, supervised_mpix=1.0,
                        gaussians=10)
    q_good, q_bad = -10 * math.log10(0.0625 ** 2), -10 * math.log10(0.125 ** 2)  # 24.08 dB, 18.06 dB
    q = dict(zip(map(tuple, ev.regional.keys.tolist()), ev.regional.q.tolist()))
    assert q[(0, 0, 2)] == pytest.approx(q_good) and q[(1, 0, 2)] == pytest.approx(q_bad)
    assert rec["cvq"] == pytest.approx((q_good + q_bad) / 2) and rec["cuc20"] == 0.5
    # CUC counts q_c >= Q: a threshold exactly at a cell's PSNR includes it, the next float above excludes it
    for threshold, expected in [(q[(1, 0, 2)], 1.0), (np.nextafter(q[(1, 0, 2)], np.inf), 0.5),
                                (q[(0, 0, 2)], 0.5), (np.nextafter(q[(0, 0, 2)], np.inf), 0.0)]:
        ev = two_cell_evaluator(quality_threshold=float(threshold))
        rec = ev.checkpoint(split_render(0.0625, 0.125), t_s=1.0, progress=1.0, updates=100, supervised_mpix=1.0,
                            gaussians=10)
        assert rec["cuc20"] == expected, threshold


def test_missing_render_counts_as_failure():
    ev = two_cell_evaluator()
    rec = ev.checkpoint(render_from(lambda f: f.color.clone() if f.index == 0 else None), t_s=0.0, progress=1.0,
                        updates=0, supervised_mpix=0.0, gaussians=0)
    # each cell: 200 perfect samples from view 0 and 200 samples of error 1.0 from the missing view 1 -> e_c = 0.5
    assert rec["cvq"] == pytest.approx(-10 * math.log10(0.5)) and rec["cuc20"] == 0.0
    assert rec["psnr"] == pytest.approx((PSNR_CAP + 0.0) / 2) and rec["missing_views"] == 1
    rec = ev.checkpoint(render_from(lambda f: None), t_s=0.0, progress=1.0, updates=0, supervised_mpix=0.0,
                        gaussians=0)
    assert rec["psnr"] == 0.0 and rec["cvq"] == 0.0 and rec["ssim"] == 0.0
    assert rec["depth_rmse_m"] == pytest.approx(WALL_Z)  # missing depth scored as 0 m


# --- CVQ-AUC -----------------------------------------------------------------------------------------------------
def test_auc_of_constant_curve_is_the_constant():
    assert cvq_auc([0.1, 0.3, 0.35, 1.0], [22.5] * 4) == pytest.approx(22.5)
    assert cvq_auc([0.4], [17.0]) == 17.0
    assert cvq_auc([0.5, 0.5], [10.0, 20.0]) == 15.0  # zero span: mean


def test_auc_of_linear_ramp_and_undefined_points():
    p = np.linspace(0.2, 1.0, 9)
    assert cvq_auc(list(p), list(10 + 5 * p)) == pytest.approx(10 + 5 * 0.6)  # mean of a ramp over [0.2, 1]
    # checkpoints before any cell is evaluable (None / NaN) are dropped: the integral starts at the first defined one
    assert cvq_auc([0.0, 0.1, 0.2, 0.6, 1.0], [None, float("nan"), 10.0, 14.0, 18.0]) == pytest.approx(14.0)
    assert cvq_auc([0.0, 0.5], [None, None]) is None
    # unnormalised integral of a step-free curve visited out of order equals the sorted one
    assert cvq_auc([1.0, 0.0], [2.0, 0.0]) == pytest.approx(1.0)


def test_curve_auc_and_final_metrics():
    ev = two_cell_evaluator()
    for i, p in enumerate([0.25, 0.5, 1.0]):
        ev.checkpoint(offset(0.1), t_s=float(i), progress=p, updates=100 * i, supervised_mpix=0.5 * i,
                      gaussians=10 * i, extra={"dropped": 0})
    assert [r["dropped"] for r in ev.curve] == [0, 0, 0]
    out = ev.final(offset(0.1))
    assert out["psnr"] == pytest.approx(20.0, abs=1e-4) and out["cvq_final"] == pytest.approx(20.0, abs=1e-4)
    assert out["cvq_auc"] == pytest.approx(20.0, abs=1e-4)
    assert out["depth_rmse_m"] == 0.0 and out["depth_rmse_2m_m"] == 0.0
    assert 0.0 < out["ssim"] <= 1.0 and len(out["per_view"]) == 2
    assert out["cells"]["keys"] and out["n_evaluable"] == 2
    json.dumps(out)  # JSON-serialisable as it is


def test_evaluation_time_is_accounted_separately():
    ev = evaluator([make_frame(0), make_frame(1)])

    def slow(frame):
        time.sleep(0.05)
        return perfect(frame)
    before = ev.eval_seconds
    rec = ev.checkpoint(slow, t_s=0.0, progress=0.0, updates=0, supervised_mpix=0.0, gaussians=0)
    assert rec["eval_s"] >= 0.1 and ev.eval_seconds - before >= 0.1
    with ev.timed():
        time.sleep(0.02)
    assert ev.eval_seconds - before >= 0.12


# --- outputs -----------------------------------------------------------------------------------------------------
def test_plots_are_written(tmp_path):
    ev = two_cell_evaluator()
    ev.checkpoint(perfect, t_s=0.0, progress=0.5, updates=0, supervised_mpix=0.0, gaussians=0)
    ev.checkpoint(split_render(0.0625, 0.125), t_s=2.0, progress=1.0, updates=100, supervised_mpix=1.0,
                  gaussians=5)
    final = ev.final(split_render(0.0625, 0.125))
    metrics = {"curve": ev.curve, "heldout": {"psnr": final["psnr"]}}
    paths = write_plots(metrics, tmp_path / "plots", cells=final["cells"])
    names = {p.name for p in paths}
    assert {"heldout_quality_vs_time.png", "heldout_quality_vs_progress.png", "cuc20_vs_progress.png",
            "cell_psnr_topdown.png"} <= names
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    assert write_plots({}, tmp_path / "empty") == []


def test_compare_table_lists_folders(tmp_path):
    for name, psnr_db, lp in [("full", 21.52, 0.32), ("no_sched", 20.1, None)]:
        d = tmp_path / name
        d.mkdir()
        (d / "metrics.json").write_text(json.dumps({
            "map_state": "ME", "heldout": {"psnr": psnr_db, "ssim": 0.757, "lpips": lp, "depth_rmse_m": 0.1},
            "cvq_auc": 19.5, "cuc20_final": 0.654, "supervised_mpix": 123.4, "gaussians": 328100,
            "mapping_time_s": 176.1, "rtf": 0.9}))
    table = compare_results([tmp_path / "full", tmp_path / "no_sched"])
    lines = table.splitlines()
    assert "full" in lines[0] and "no_sched" in lines[0]
    row = {ln.split("  ")[0].strip(): ln.split() for ln in lines[2:]}
    assert "21.52" in row["PSNR [dB] (paper's rule)"] and "20.10" in row["PSNR [dB] (paper's rule)"]
    assert "0.320" in row["LPIPS"] and "-" in row["LPIPS"]
    assert "65.4" in table and "328100" in table
    # a pose-refined run: the paper's rule (aligned) leads, carried is labelled as the map's refined frame
    d = tmp_path / "refined"
    d.mkdir()
    (d / "metrics.json").write_text(json.dumps({
        "heldout": {"psnr": 22.5}, "heldout_pose_rule": "carried", "heldout_given_poses": {"psnr": 20.25},
        "heldout_by_pose_rule": {"aligned": {"psnr": 20.75}, "carried": {"psnr": 22.5}, "given": {"psnr": 20.25}}}))
    lines = compare_results([d]).splitlines()
    row = {ln.split("  ")[0].strip(): ln.split() for ln in lines[2:]}
    assert "20.75" in row["PSNR [dB] (paper's rule)"]
    assert "22.50" in row["PSNR in the map's refined frame (carried) [dB]"]
    assert "20.25" in row["PSNR at given poses [dB]"]
    assert [ln.split("  ")[0] for ln in lines[4:7]] == ["PSNR [dB] (paper's rule)",
                                                       "PSNR in the map's refined frame (carried) [dB]",
                                                       "PSNR at given poses [dB]"]
    with pytest.raises(FileNotFoundError, match="metrics.json"):
        compare_results([tmp_path / "nope"])
