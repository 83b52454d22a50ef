"""The map's low-pass (GaussianMap.low_pass): a map drawn finer than it was supervised gets the screen-space filter
of its supervising pixels. Every renderer takes ``low_pass``; the compiled one matches the torch reference with it,
the view test keeps every Gaussian the wider footprint reaches, the map records its supervision through updates,
checkpoints and PLY files, and the public render uses it."""

import numpy as np
import pytest
import torch

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import EPS2D, GaussianMap
from eligsir_o3d.io.ply import PlyError, load_ply, save_ply
from eligsir_o3d.render import get_renderer
from eligsir_o3d.render.cpu_backend import CpuRenderer
from eligsir_o3d.render.culling import in_view
from tests.render.test_render_agreement import assert_grads_close, edge_case_scene, render_with_grads

CAM = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)


def test_low_pass_follows_the_finest_supervising_focal_length():
    gm = GaussianMap()
    assert gm.supervision_focal is None and gm.low_pass(CAM) == EPS2D  # never supervised: 3DGS's 0.3 px^2
    gm.note_supervision(CAM.scaled(0.25))
    assert gm.supervision_focal == pytest.approx(15.0)
    assert gm.low_pass(CAM) == pytest.approx(EPS2D * 16)  # drawn 4x finer: the 1/4-scale pixel's filter
    assert gm.low_pass(CAM.scaled(0.5)) == pytest.approx(EPS2D * 4)
    assert gm.low_pass(CAM.scaled(0.125)) == EPS2D  # coarser than supervised: never below 0.3
    gm.note_supervision(CAM.scaled(0.5))  # a finer update lowers it; a coarser one later does not raise it
    gm.note_supervision(CAM.scaled(0.25))
    assert gm.low_pass(CAM) == pytest.approx(EPS2D * 4)


@pytest.mark.parametrize("low_pass", [1.2, 4.8])
def test_cpu_matches_reference_with_a_wider_low_pass(low_pass):
    params, T = edge_case_scene(seed=2)
    bg = torch.tensor([0.2, 0.4, 0.6])

    def run(renderer):
        class WithLowPass:  # render_with_grads calls render(...) without the keyword
            def render(self, *a, **kw):
                return renderer.render(*a, low_pass=low_pass, **kw)

        return render_with_grads(WithLowPass(), params, CAM, T, bg)

    ref_out, ref_g = run(get_renderer("torch"))
    out, g = run(CpuRenderer())
    plain, _ = render_with_grads(get_renderer("torch"), params, CAM, T, bg)
    for name in ("color", "depth", "alpha"):
        torch.testing.assert_close(getattr(out, name), getattr(ref_out, name), atol=2e-5, rtol=1e-4)
    assert torch.equal(out.radii, ref_out.radii)
    assert_grads_close(g, ref_g, rtol=2e-3, atol_frac=2e-4)
    assert (ref_out.radii >= plain.radii).all() and (ref_out.radii > plain.radii).any()  # footprints grow
    assert float((ref_out.color - plain.color).detach().abs().max()) > 1e-3  # and the image changes


def test_view_test_keeps_what_the_wider_footprint_draws():
    """Tiny Gaussians just outside the image: drawn only through the low-pass, and the view test keeps them."""
    g = torch.Generator().manual_seed(5)
    n = 3000
    u = torch.empty(n).uniform_(-8.0, CAM.width + 8.0, generator=g)
    v = torch.empty(n).uniform_(-8.0, CAM.height + 8.0, generator=g)
    z = torch.empty(n).uniform_(1.0, 4.0, generator=g)
    means = torch.stack([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z], -1)
    gm = GaussianMap()
    gm.add(means, torch.rand(n, 3, generator=g), torch.full((n,), 1e-4), 0.9)
    r = get_renderer("cpu")
    for lp in (EPS2D, 4.8, 20.0):
        out = r.render(*gm.render_args(), CAM, np.eye(4), low_pass=lp)
        drawn = torch.nonzero(out.radii > 0).squeeze(1)
        kept = in_view(gm.params["means"], gm.params["scales"], CAM, np.eye(4), lp)
        assert bool(torch.isin(drawn, kept).all()), lp
        if lp == 20.0:
            assert len(drawn) > len(torch.nonzero(r.render(*gm.render_args(), CAM, np.eye(4)).radii).squeeze(1))


def test_supervision_focal_survives_ply_and_state(tmp_path):
    gm = GaussianMap()
    gm.add(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([0.05]), 0.5)
    assert load_ply(save_ply(gm, tmp_path / "a.ply")).supervision_focal is None  # none recorded: none written
    gm.note_supervision(Camera(160, 120, 131.25, 131.0, 79.5, 59.5))
    back = load_ply(save_ply(gm, tmp_path / "b.ply"))
    assert back.supervision_focal == gm.supervision_focal
    other = GaussianMap()
    other.load_state_dict(gm.state_dict())
    assert other.supervision_focal == gm.supervision_focal
    old = gm.state_dict()
    del old["supervision_focal"]  # a checkpoint written before it was kept
    other.load_state_dict(old)
    assert other.supervision_focal is None


def test_bad_supervision_comment_names_the_file(tmp_path):
    gm = GaussianMap()
    gm.add(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([0.05]), 0.5)
    gm.note_supervision(CAM)
    p = save_ply(gm, tmp_path / "m.ply")
    data = p.read_bytes()
    bad = data.replace(f"supervision_focal_px {gm.supervision_focal!r}".encode(), b"supervision_focal_px -1x")
    (tmp_path / "bad.ply").write_bytes(bad)
    with pytest.raises(PlyError, match=r"bad\.ply.*supervision_focal_px"):
        load_ply(tmp_path / "bad.ply")


def test_updates_record_their_scale_and_the_public_render_uses_it():
    from eligsir_o3d.datasets import open_sequence

    seq = open_sequence("synthetic", n_frames=4, width=80, height=60)
    frames = [seq.frame(i) for i in range(4)]
    rec = Reconstructor(seq.camera, "cpu", Config(renderer="cpu"))
    for f in frames:
        rec.integrate(f, updates=2)
    assert rec.stats.updates > 0 and rec.gmap.supervision_focal is not None
    s = rec.gmap.supervision_focal / rec.camera.fx
    assert s < 1.0  # supervised below full size, as the budget's scales are
    lp = rec.gmap.low_pass(rec.camera)
    assert lp == pytest.approx(EPS2D / (s * s), rel=0.05)
    T = frames[1].T_world_cam
    got = rec.render(T)
    with torch.no_grad():
        want = rec.renderer.render(*rec.gmap.render_args(), rec.camera, T, rec._background, low_pass=lp)
        plain = rec.renderer.render(*rec.gmap.render_args(), rec.camera, T, rec._background)
    torch.testing.assert_close(got.color, want.color.clamp(0, 1), atol=1e-6, rtol=0)
    assert float((got.color - plain.color.clamp(0, 1)).abs().max()) > 1e-3
