"""The fused (CUDA) path's budget, counted on the CPU (benchmarks/speed/update_launches.py): kernel launches,
host synchronisations and host-device copies of one update, gsplat's modelled, a regression fails here."""

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("gsplat")
pytest.importorskip("triton")

ROOT = Path(__file__).resolve().parents[2]
DEVICE = ("select", "render", "backward", "step", "mcmc", "feedback", "triton")


def _harness():
    spec = importlib.util.spec_from_file_location("update_launches", ROOT / "benchmarks/speed/update_launches.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def counts():
    h = _harness()
    return h, h.count_update("fused", updates=4, frames=6)


def test_fused_update_fits_the_launch_and_sync_budget(counts):
    h, r = counts
    ph = r["by_phase"]
    launches = sum(ph.get(p, {}).get("launches", 0.0) for p in DEVICE)
    syncs = sum(ph.get(p, {}).get("syncs", 0.0) for p in DEVICE)
    copies = sum(ph.get(p, {}).get("copies", 0.0) for p in DEVICE)
    assert ph["render"]["launches"] == h.GSPLAT_FWD and ph["render"]["syncs"] == 1  # gsplat's own, modelled
    assert ph["triton"]["launches"] == 7  # select 2, loss 2, step 1, the views' feedback 2
    assert launches <= 40, ph
    assert syncs <= 1, ph  # gsplat's tile-intersection count only
    # one 8-byte asynchronous copy of the view's row count (pinned, completed by gsplat's own sync), nothing else
    assert ph["select"]["copies"] <= 1 and copies - ph["select"]["copies"] == 0, {p: ph[p]["copies"] for p in ph}
    assert r["in_view"] > 0


def test_views_feedback_is_device_work(counts):
    """The views' feedback folds the error map into the microcells on the device (its two Triton launches are in
    ``triton``): no other launch, no sync, no copy; a view's plan (which pixels fall in which cells) is made once
    per resolution, on the host, in its own phase."""
    _, r = counts
    fb = r["by_phase"].get("feedback", {"launches": 0, "syncs": 0, "copies": 0})
    assert fb["launches"] == 0 and fb["syncs"] == 0 and fb["copies"] == 0, fb


def test_the_counter_sees_a_sync_and_a_copy():
    """The rules count what they should: an ``.item()`` in a device phase is a sync and a transfer."""
    import torch

    h = _harness()
    c = h.Counts()
    with h._Functions(c), h._Dispatch(c), c.within("step"):
        x = torch.ones(3) * 2
        float(x.sum().item())
    assert c.syncs["step"] >= 1 and c.copies["step"] >= 1 and c.launches["step"] >= 2
