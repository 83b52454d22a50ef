"""eligsir_o3d.export.viewers: a map baked for viewers with 3DGS's fixed 0.3 px^2 low-pass draws there as this
package draws the map with its own low-pass; depths come from the nearest view that sees each Gaussian; the CLI
writes it from a results folder and names what is missing."""

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from eligsir_o3d import Config
from eligsir_o3d.cli.app import app
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import EPS2D, GaussianMap
from eligsir_o3d.export.viewers import baked_for_viewers, nearest_depths, write_for_viewers
from eligsir_o3d.export.views import camera_next_to, poses_next_to
from eligsir_o3d.export.web import write_web
from eligsir_o3d.io.ply import load_ply, save_ply
from eligsir_o3d.render import get_renderer
from eligsir_o3d.run.pipeline import RunOptions, run_mapping

CAM = Camera(96, 72, 90.0, 90.0, 47.5, 35.5)


def _near_axis_map(n=60, seed=0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    z = torch.empty(n).uniform_(1.5, 3.0, generator=g)
    xy = torch.empty(n, 2).uniform_(-0.25, 0.25, generator=g) * z[:, None]
    gm = GaussianMap()
    sizes = torch.empty(n).uniform_(0.002, 0.01, generator=g)
    gm.add(torch.cat([xy, z[:, None]], 1), torch.rand(n, 3, generator=g), sizes, 0.6)
    gm.note_supervision(CAM.scaled(0.25))
    return gm


def test_baked_map_at_the_fixed_low_pass_draws_as_the_map_with_its_own():
    gm = _near_axis_map()
    baked = baked_for_viewers(gm, CAM, [np.eye(4)])
    assert baked.supervision_focal == pytest.approx(90.0) and baked.low_pass(CAM) == EPS2D
    assert (baked.scales > gm.scales).all()  # widened; the original is untouched
    r = get_renderer("torch")
    ours = r.render(*gm.render_args(), CAM, np.eye(4), low_pass=gm.low_pass(CAM))
    viewer = r.render(*baked.render_args(), CAM, np.eye(4))  # what a 0.3 px^2 viewer draws
    plain = r.render(*gm.render_args(), CAM, np.eye(4))
    diff, gap = (viewer.color - ours.color).detach().abs(), (plain.color - ours.color).detach().abs()
    # isotropic splats near the axis: the 3D widening is the 2D low-pass to first order (measured: max 0.025,
    # mean 0.0011 of [0, 1] colour, against 0.68 / 0.060 for the map drawn with 0.3 px^2 unbaked)
    assert float(diff.max()) < 0.05 and float(diff.mean()) < 0.003, (float(diff.max()), float(diff.mean()))
    assert float(gap.mean()) > 10 * float(diff.mean())  # and the bake is what makes the difference


def test_nothing_to_bake_when_drawn_at_the_supervised_scale():
    gm = _near_axis_map()
    baked = baked_for_viewers(gm, CAM.scaled(0.25), [np.eye(4)])
    torch.testing.assert_close(baked.scales, gm.scales)


def test_nearest_depths_takes_the_closest_view_that_sees_a_point():
    pts = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -5.0]])
    near = np.eye(4)
    near[2, 3] = 1.0  # one metre closer to the first point
    d = nearest_depths(pts, CAM, [np.eye(4), near])
    assert d[0] == pytest.approx(2.0)
    assert d[1] == pytest.approx(5.0)  # behind every view: its distance to the nearest camera centre


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("baked_run")
    cfg = Config(renderer="cpu")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 0
    cfg.supervision.mode = "area"  # fitted below full size, what the bake is for (the room would measure "point")
    cfg.fidelity.scales = (0.25, 0.5)  # below full size whatever the cost model prices (the shipped one since stop
    # 47 lets this small room's updates reach full size)
    run_mapping("synthetic", out, cfg, RunOptions(max_frames=8, holdout_every=4, eval_every=0, progress=False,
                                                  plots=False, pictures=False, formats="ply,splat"))
    return out


def test_cli_writes_the_baked_map_from_a_results_folder(run_folder, tmp_path):
    out = tmp_path / "viewers.ply"
    res = CliRunner().invoke(app, ["export", str(run_folder / "map.ply"), "--for-viewers", str(out)])
    assert res.exit_code == 0, res.output
    gm, baked = load_ply(run_folder / "map.ply"), load_ply(out)
    assert len(baked) == len(gm) and "baked_low_pass_px2" in res.output
    assert gm.supervision_focal < baked.supervision_focal  # supervised below full size; baked: full
    assert (baked.scales >= gm.scales * (1 - 1e-6)).all() and (baked.scales > gm.scales).any()


def test_missing_camera_or_poses_and_overwriting_are_clear_errors(run_folder, tmp_path):
    gm = load_ply(run_folder / "map.ply")
    lone = save_ply(gm, tmp_path / "lone" / "map.ply")
    with pytest.raises(ValueError, match="no camera beside the map"):
        write_for_viewers(lone, tmp_path / "a.ply")
    with pytest.raises(ValueError, match="trajectory.txt does not exist"):
        write_for_viewers(lone, tmp_path / "a.ply", camera=CAM)
    with pytest.raises(ValueError, match="would overwrite the input"):
        write_for_viewers(run_folder / "map.ply", run_folder / "map.ply")
    res = CliRunner().invoke(app, ["export", str(lone), "--for-viewers", str(tmp_path / "b.ply")])
    assert res.exit_code == 2 and "no camera beside the map" in res.output


def _splat_bytes(gm: GaussianMap, tmp_path, name: str) -> bytes:
    """The .splat that write_web makes of ``gm`` as it is (no camera: no bake)."""
    write_web(gm, splat=tmp_path / "plain" / f"{name}.splat")
    return (tmp_path / "plain" / f"{name}.splat").read_bytes()


def test_web_formats_carry_the_baked_low_pass(tmp_path):
    """Web players add 0.3 px^2 whatever the map was fitted at, so .splat / SPZ get the bake; a map drawn at its
    supervised scale, or one without poses, is written as it is."""
    gm = _near_axis_map()
    out = tmp_path / "out"
    s = write_web(gm, splat=out / "a.splat", camera=CAM, poses=[np.eye(4)])
    assert s["baked_low_pass_px2"] == pytest.approx(gm.low_pass(CAM)) and s["gaussians"] == len(gm)
    plain = _splat_bytes(gm, tmp_path, "plain")
    assert (out / "a.splat").read_bytes() == _splat_bytes(baked_for_viewers(gm, CAM, [np.eye(4)]), tmp_path, "b")
    assert (out / "a.splat").read_bytes() != plain
    for cam, poses in ((CAM.scaled(0.25), [np.eye(4)]), (CAM, None)):
        s = write_web(gm, splat=out / "b.splat", camera=cam, poses=poses)
        assert s["baked_low_pass_px2"] == EPS2D and (out / "b.splat").read_bytes() == plain
    assert sorted(p.name for p in out.iterdir()) == ["a.splat", "b.splat"]  # no temporary file left


def test_map_and_export_write_baked_web_formats(run_folder, tmp_path):
    gm = load_ply(run_folder / "map.ply")
    written = (run_folder / "map.splat").read_bytes()  # eligsir map --format ply,splat
    assert gm.low_pass(Camera(**json.loads((run_folder / "run.json").read_text())["camera"])) > EPS2D
    assert len(written) == 32 * len(gm) and written != _splat_bytes(gm, tmp_path, "unbaked")
    res = CliRunner().invoke(app, ["export", str(run_folder / "map.ply"), "--splat", str(tmp_path / "e.splat")])
    assert res.exit_code == 0 and "baked_low_pass_px2" in res.output, res.output
    assert (tmp_path / "e.splat").read_bytes() == written
    lone = save_ply(gm, tmp_path / "lone" / "map.ply")  # no run.json nor trajectory beside it: as it is
    assert camera_next_to(lone) is None and poses_next_to(lone) is None
    res = CliRunner().invoke(app, ["export", str(lone), "--splat", str(tmp_path / "f.splat")])
    assert res.exit_code == 0 and "baked_low_pass_px2: 0.3" in res.output, res.output


def test_viewer_draws_a_results_folder_baked(run_folder, tmp_path):
    """eligsir view (viser adds 0.3 px^2): a results folder's map is shown with its low-pass baked in, a lone PLY
    as it is."""
    from eligsir_o3d.visual.splats import read_splats

    gm = load_ply(run_folder / "map.ply")
    shown, plain = read_splats(run_folder / "map.ply"), read_splats(run_folder / "map.ply", bake=False)
    tr = lambda s: np.trace(s.covariances, axis1=1, axis2=2)  # noqa: E731
    assert len(shown) == len(plain) == len(gm)
    assert (tr(shown) >= tr(plain) * (1 - 1e-5)).all() and (tr(shown) > tr(plain) * 1.01).any()
    lone = save_ply(gm, tmp_path / "lone" / "map.ply")
    np.testing.assert_allclose(tr(read_splats(lone)), tr(plain), rtol=1e-6)
