"""The spatial row index of large maps (eligsir_o3d.render.cell_index): it returns exactly the rows the plain view
test keeps, for any pose, and stays exact while a mapping run moves, adds, relocates and removes rows."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import PARAM_NAMES, GaussianMap
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.render import cell_index
from eligsir_o3d.render.culling import in_view, map_in_view

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def _clustered_map(n: int, seed: int) -> GaussianMap:
    """Rows in clusters (rooms) over a 40 m scene, in random row order, with a few huge and tiny scales."""
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(12, 3, generator=g) - 0.5) * 40.0
    means = centres[torch.randint(0, 12, (n,), generator=g)] + torch.randn(n, 3, generator=g) * 1.5
    scales = torch.exp(torch.empty(n).uniform_(np.log(1e-4), np.log(0.3), generator=g))
    scales[:5] = 2.0e5  # beyond the row test's clamp: kept wherever they are in front
    gm = GaussianMap(0)
    gm.add(means, torch.rand(n, 3, generator=g), scales, 0.5)
    return gm


def _poses(seed: int, k: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(k):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        T[:3, 3] = rng.uniform(-22, 22, 3)
        out.append(T)
    return out


@pytest.fixture
def small_groups(monkeypatch):
    """The index on any map, in groups of 16 rows (many groups on a test-sized map)."""
    monkeypatch.setattr(cell_index, "MIN_ROWS", 0)
    monkeypatch.setattr(cell_index, "GROUP", 16)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_index_returns_exactly_the_rows_of_the_plain_test(small_groups, seed):
    gm = _clustered_map(20000, seed)
    for T in _poses(seed, 25):
        for low_pass in (0.3, 4.8):
            want = in_view(gm.params["means"], gm.params["scales"], CAM, T, low_pass)
            got = map_in_view(gm, CAM, T, low_pass)
            assert torch.equal(got, want)
    assert gm.row_index is not None and gm.row_index.builds == 1


def test_index_drops_most_groups_of_a_view_that_sees_little(small_groups):
    gm = _clustered_map(20000, 3)
    T = np.eye(4)
    T[:3, 3] = [60.0, 0.0, 0.0]  # outside the scene, looking along +z: nothing ahead
    got = map_in_view(gm, CAM, T)
    assert torch.equal(got, in_view(gm.params["means"], gm.params["scales"], CAM, T))
    assert bool((got < 5).all())  # only huge Gaussians (those in front of the camera)
    idx = gm.row_index
    from eligsir_o3d.render._cull_kernels import groups_hit
    from eligsir_o3d.render.culling import camera_bounds
    from eligsir_o3d.render.projection import world_to_cam

    kept = groups_hit(idx.boxes, world_to_cam(T, "cpu", torch.float64).numpy(), camera_bounds(CAM))
    assert kept.sum() <= 5  # only the groups holding a huge Gaussian


def test_index_follows_moved_appended_assigned_and_removed_rows(small_groups):
    gm = _clustered_map(6000, 4)
    poses = _poses(4, 12)
    g = torch.Generator().manual_seed(5)

    def check():
        for T in poses:
            want = in_view(gm.params["means"], gm.params["scales"], CAM, T)
            assert torch.equal(map_in_view(gm, CAM, T), want)

    check()
    builds = gm.row_index.builds
    rows = torch.randperm(len(gm), generator=g)[:500]  # moved in place (as Adam or the noise would), then told
    with torch.no_grad():
        gm.params["means"][rows] += torch.randn(500, 3, generator=g) * 10.0
        gm.params["scales"][rows] += 2.0
    gm.touched(rows)
    check()
    gm.add(torch.randn(800, 3, generator=g) * 10.0, torch.rand(800, 3, generator=g), torch.full((800,), 0.05), 0.5)
    check()  # appended rows: tested one by one until the next build
    assert gm.row_index.builds == builds
    src = torch.randint(0, len(gm), (300,), generator=g)
    gm.assign(torch.randint(0, 6000, (300,), generator=g), {"means": gm.params["means"].detach()[src] + 5.0})
    check()
    gm.remove(torch.rand(len(gm), generator=g) < 0.2)
    check()  # new row ids: rebuilt
    assert gm.row_index.builds == builds + 1
    gm.add(torch.randn(3000, 3, generator=g) * 10.0, torch.rand(3000, 3, generator=g), torch.full((3000,), 0.05), 0.5)
    check()  # more appended rows than a quarter of the indexed: rebuilt
    assert gm.row_index.builds == builds + 2


def _mapping_run(monkeypatch, indexed: bool) -> tuple[GaussianMap, int]:
    monkeypatch.setattr(cell_index, "MIN_ROWS", 0 if indexed else 10 ** 9)
    seq = open_sequence("synthetic", n_frames=6, width=64, height=48)
    cfg = Config(renderer="cpu", seed=0)
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 4, 4  # relocation and densification rounds
    rec = Reconstructor(seq.camera, "cpu", cfg)
    rec.set_load(0, cfg.clock.frame_period_s, cfg.clock.cost)  # the shipped cost model prices updates, not the clock
    checks = [0]
    if indexed:
        import eligsir_o3d.render.culling as culling

        indexed_test = culling.map_in_view

        def compared(gmap, camera, T, low_pass=0.3):
            got = indexed_test(gmap, camera, T, low_pass)
            assert torch.equal(got, culling.in_view(gmap.params["means"], gmap.params["scales"], camera, T, low_pass))
            checks[0] += 1
            return got

        monkeypatch.setattr(culling, "map_in_view", compared)
    for i in range(len(seq)):
        f = seq.frame(i)
        rec.integrate(f, f.T_world_cam, updates=6)
    return rec.gmap, checks[0]


def test_a_mapping_run_with_the_index_is_the_run_without_it(monkeypatch, small_groups):
    """Every view test of a run with growth, Adam, noise and relocation on an indexed map returns the plain test's
    rows, so the map comes out bit for bit the same. Both runs price updates by the shipped cost model: measured
    seconds would let the fidelity policy pick a different scale in one run than in the other."""
    a, checks = _mapping_run(monkeypatch, True)
    monkeypatch.undo()
    b, _ = _mapping_run(monkeypatch, False)
    assert checks >= 36 and a.row_index is not None and b.row_index is None
    assert len(a) == len(b)
    for n in PARAM_NAMES:
        assert torch.equal(a.params[n], b.params[n]), n
