"""Issue 31 item 14: eligsir live holds the run lock on its folder (never writing through a planted link) and
writes atomically; Reconstructor.load_state_dict is transactional (a state that fails half-way leaves the map as
it was)."""

import copy

import numpy as np
import open3d as o3d
import pytest
import torch

import eligsir_o3d as eo3d
from eligsir_o3d.run.live_run import run_live
from eligsir_o3d.run.lock import LOCK_FILE, RunLocked

W, H = 48, 36


class _Probe:
    """A frame source that records whether the lock is held when the run starts, then ends the run."""

    name, depth_scale = "probe", 1000.0
    camera = eo3d.core.camera.Camera(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2) if hasattr(eo3d, "core") else None

    def __init__(self, out):
        self.out, self.saw_lock = out, None

    def start(self):
        self.saw_lock = (self.out / LOCK_FILE).is_file()
        raise KeyboardInterrupt  # nothing more to see

    def stop(self):
        pass


def test_live_holds_the_lock_and_releases_it(tmp_path):
    from eligsir_o3d.core.camera import Camera

    _Probe.camera = Camera(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2)
    src = _Probe(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_live(src, tmp_path, eo3d.Config(renderer="torch"))
    assert src.saw_lock is True and not (tmp_path / LOCK_FILE).exists()


def test_live_refuses_a_symlinked_lock_and_a_folder_in_use(tmp_path):
    from eligsir_o3d.run.lock import RunLock

    victim = tmp_path / "victim"
    victim.write_text("keep")
    out = tmp_path / "live"
    out.mkdir()
    (out / LOCK_FILE).symlink_to(victim)
    with pytest.raises(RunLocked, match="symbolic link"):
        run_live(_Probe(out), out, eo3d.Config(renderer="torch"))
    assert victim.read_text() == "keep"
    other = tmp_path / "busy"
    with RunLock(other):  # another run of this host holds the folder (a second flock is refused)
        with pytest.raises(RunLocked, match="in use by another eligsir run"):
            run_live(_Probe(other), other, eo3d.Config(renderer="torch"))


def _rec():
    cfg = eo3d.Config(renderer="torch", ablate=("views", "fidelity", "growth"))
    cfg.keyframes.every, cfg.seeding.pixel_stride, cfg.clock.updates_per_frame = 1, 3, 2
    rec = eo3d.Reconstructor(o3d.camera.PinholeCameraIntrinsic(W, H, 40.0, 40.0, (W - 1) / 2, (H - 1) / 2), "cpu",
                             cfg)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    color = (((u // 6 + v // 6) % 2)[..., None] * np.array([180, 40, 60]) + 50).astype(np.uint8)
    rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(np.full((H, W), 1500,
                                                                                              np.uint16)))
    return rec, rgbd


@pytest.mark.parametrize("break_it", ["policy", "retained", "stats", "rng"])
def test_load_state_dict_is_transactional(break_it):
    rec, rgbd = _rec()
    rec.integrate(rgbd, np.eye(4))
    other, _ = _rec()
    other.integrate(rgbd, np.eye(4))
    other.integrate(rgbd, np.eye(4))
    state = copy.deepcopy(other.state_dict())  # a different, larger map ...
    if break_it == "policy":  # ... whose state fails after the Gaussians were loaded
        del state["policies"]["fidelity"]["state"]
    elif break_it == "retained":  # the view policy's views do not match the record: checked after the policies
        state["retained"] = []
    elif break_it == "stats":
        del state["stats"]
    else:
        state["rng"] = "not a state"
    before = {n: p.detach().clone() for n, p in rec.gmap.params.items()}
    views_before, updates_before = len(rec.views.views), rec.stats.updates
    with pytest.raises(Exception):
        rec.load_state_dict(state)
    assert {n: p.shape for n, p in rec.gmap.params.items()} == {n: p.shape for n, p in before.items()}
    assert all(torch.equal(rec.gmap.params[n].detach(), before[n]) for n in before)
    assert len(rec.views.views) == views_before and rec.stats.updates == updates_before
    rec.integrate(rgbd, np.eye(4))  # and it still maps
