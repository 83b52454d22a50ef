"""benchmarks/quality/tsdf_baseline.py on the synthetic room: the TSDF peer reads the run's own split and poses, covers
the views it was fused from, scores higher on its covered pixels than on the whole image, and the Gaussian map is
scored at the same given poses as the pipeline's own evaluation."""

import json

import numpy as np
import pytest

from eligsir_o3d import Config
from eligsir_o3d.run.pipeline import RunOptions, run_mapping
from helpers.scripts import load_script, synthetic_run


def _baseline():
    return load_script("benchmarks/quality/tsdf_baseline.py")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    return synthetic_run(tmp_path_factory.mktemp("tsdf_run"), updates_per_frame=3, drain_updates=10)


def test_tsdf_peer_of_a_run(run_folder, tmp_path):
    tb = _baseline()
    r = tb.evaluate(run_folder, pictures=tmp_path / "pics", picture_views=(0,))
    metrics = json.loads((run_folder / "metrics.json").read_text())
    assert r["views"] == metrics["frames_heldout"] == 4
    assert r["frames_source"] == metrics["frames_source"] == 12
    assert 0.5 < r["coverage"] <= 1.0  # held-out views sit between fused views of the same room
    assert r["tsdf_covered"] >= r["tsdf_whole"]  # unobserved pixels are black
    assert r["tsdf_covered"] > 18.0  # exact depth and poses: the fused colour matches the reference
    # the Gaussian map is rendered at the given poses exactly as the pipeline evaluated it
    assert r["gaussian_whole"] == pytest.approx(metrics["heldout"]["psnr"], abs=1e-3)
    assert "gaussian_aligned_whole" not in r  # no refinement, no aligned rule
    # where the error lies: defined for both renders; exact poses, so neither is better off shifted far
    for name in ("gaussian", "tsdf"):
        assert r[f"{name}_lowpass"] > r[f"{name}_detail"]  # the error is in the detail more than in broad colour
        assert r[f"{name}_shifted"] >= r[f"{name}_covered"] - 1.0  # the border is left out; a shift never loses more
        assert r[f"{name}_shift_px"] <= 2.0
    assert {"gaussian_shift_dx", "tsdf_shift_dy"} <= set(r["per_view"][0])
    assert "gaussian_shift_dx" not in r  # a mean signed shift says nothing: per view only
    assert "where the error lies" in tb.format_table(r)
    margins = [v["gaussian_covered"] - v["tsdf_covered"] for v in r["per_view"]]  # 4 views: thirds of 2, 1, 1
    assert r["margin_by_third"] == pytest.approx([np.mean(margins[:2]), margins[2], margins[3]])
    assert "by thirds" in tb.format_table(r)
    assert r["pose_suspects"] == []  # exact poses: no held-out view is off
    pics = sorted((tmp_path / "pics").glob("*.png"))
    assert len(pics) == 1  # Gaussian | TSDF | reference, side by side
    import imageio.v3 as iio

    im = iio.imread(pics[0])
    assert im.shape[1] == 3 * 160 + 2 * 4 and im.shape[0] == 120


def test_mesh_render_depth_matches_the_fused_depth(run_folder):
    """The ray-cast TSDF surface lies where integrate put it: each view fused alone and rendered at its own pose
    gives back its depth to within a voxel (a camera-to-world extrinsic would be off by decimetres)."""
    tb = _baseline()
    seq, cfg, _, source, _, poses = tb.read_results(run_folder)
    bias = []
    for i in source[:4]:
        vbg, _ = tb.fuse(seq, {i: poses[i]}, cfg.depth_max)
        r = tb.MeshRenderer(vbg.extract_triangle_mesh(weight_threshold=0.5))  # one frame: weight 1
        f = seq.frame(i)
        _, depth = r.render(seq.camera, f.T_world_cam)
        m = (depth > 0) & (f.depth.numpy() > 0)
        assert m.mean() > 0.8
        bias.append(float(np.median(depth[m] - f.depth.numpy()[m])))
    assert np.abs(bias).max() < 0.01  # metres (measured: 5-8 mm, the one-view TSDF's zero crossing)


def test_a_folder_without_a_run_record_is_a_clear_error(tmp_path):
    tb = _baseline()
    with pytest.raises(ValueError, match="run.json"):
        tb.evaluate(tmp_path)


def test_a_run_without_held_out_views_is_a_clear_error(tmp_path):
    """A recording too short for the split (4 frames, every 8th held out) has nothing to score: say so."""
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 1, 0
    run_mapping("synthetic", tmp_path, cfg, RunOptions(max_frames=4, holdout_every=8, eval_every=0, progress=False,
                                                       plots=False, pictures=False))
    tb = _baseline()
    with pytest.raises(ValueError, match="held out no views"):
        tb.evaluate(tmp_path)
    assert tb.main([str(tmp_path)]) == 2


def test_pose_suspects_are_views_both_renders_match_shifted_alike():
    def row(i, g, t):
        return {"index": i, "gaussian_shift_dx": g[0], "gaussian_shift_dy": g[1], "tsdf_shift_dx": t[0],
                "tsdf_shift_dy": t[1], "gaussian_covered": 15.0, "gaussian_shifted": 23.0, "tsdf_covered": 15.5,
                "tsdf_shifted": 23.5}

    rows = [row(0, (0, -11), (-1, -12)),  # both far and alike: the given pose is off
            row(1, (5, 0), (-5, 0)),  # both far, opposite ways: the maps disagree, not a pose
            row(2, (1, 0), (1, 1)),  # near
            row(3, (6, 0), (0, 0))]  # one map only
    tb = _baseline()
    sus = tb.pose_suspects(rows)
    assert [s["index"] for s in sus] == [0]
    assert sus[0]["shift_px"] == [0, -11] and sus[0]["gaussian"] == [15.0, 23.0] and sus[0]["tsdf"] == [15.5, 23.5]
    text = tb.format_table({"results": "r", "views": 4, "frames_source": 10, "voxel_size_m": 0.01,
                            "tsdf_integrate_ms_per_frame": 1.0, "gaussians": 5, "tsdf_whole": 1.0, "coverage": 0.9,
                            "tsdf_covered": 1.0, "gaussian_whole": 1.0, "gaussian_covered": 1.0,
                            "gaussian_detail": 1.0, "tsdf_detail": 1.0, "gaussian_flat": 1.0, "tsdf_flat": 1.0,
                            "gaussian_lowpass": 1.0, "tsdf_lowpass": 1.0, "gaussian_shift_px": 1.0,
                            "tsdf_shift_px": 1.0, "gaussian_shifted": 1.0, "tsdf_shifted": 1.0,
                            "pose_suspects": sus})
    assert "frame 0 by (+0, -11) px" in text
