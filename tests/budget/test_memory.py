"""Memory bounds: a long stream never takes the map past the Gaussian cap or the views past their bound."""

import pytest

import eligsir_o3d as eo3d
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.budget.memory import current_rss_mb, map_memory_mb, memory_report, peak_rss_mb, views_memory_mb

CAP, MAX_VIEWS, FRAMES = 120, 3, 24


@pytest.fixture(scope="module")
def frames():
    seq = open_sequence("synthetic", n_frames=FRAMES, width=32, height=24)
    return seq, [seq.frame(i) for i in range(FRAMES)]


@pytest.mark.parametrize("ablate", [(), ("views", "fidelity", "growth")], ids=["eligsir", "plain"])
def test_long_stream_stays_within_caps(frames, ablate):
    seq, fs = frames
    cfg = eo3d.Config(ablate=ablate, max_gaussians=CAP)
    cfg.depth_scale = seq.depth_scale
    cfg.seeding.pixel_stride = 2  # seeds far more than the cap allows
    cfg.keyframes.every, cfg.keyframes.max_views = 1, MAX_VIEWS
    cfg.views.max_views = MAX_VIEWS  # the EliGSiR view policy's bound (the plain one's is keyframes.max_views)
    cfg.support.scale, cfg.growth.seed_stride = 1.0, 1
    rec = eo3d.Reconstructor(seq.intrinsic, "cpu", cfg)
    most_g = most_v = 0
    for f in fs:
        rec.integrate(f, updates=1)
        most_g, most_v = max(most_g, len(rec.gmap)), max(most_v, len(rec.views.views))
        assert len(rec.gmap) <= CAP and len(rec.views.views) <= MAX_VIEWS, (f.index, len(rec.gmap), len(rec.views.views))
    rec.gmap.check_aligned()
    assert most_g > CAP // 2 and most_v == MAX_VIEWS  # the caps were reached, not just never approached
    r = memory_report(rec)
    assert r["retained_views"] <= MAX_VIEWS and r["gaussians"] <= CAP
    assert 0 < r["views_mb"] <= MAX_VIEWS * 32 * 24 * 16 * (4 / 3) / 2**20 + 1e-9  # colour + depth + pyramid
    assert 0 < r["map_mb"] == map_memory_mb(rec.gmap)


def test_rss_helpers_see_an_allocation():
    """A buffer 200 MiB larger than the gap between the current RSS and the peak so far (importing torch peaks
    above where it settles), touched, shows up in the current RSS and lifts the peak; freed, it leaves the RSS."""
    import json
    import subprocess
    import sys

    code = ("import json, numpy as np; from eligsir_o3d.budget.memory import current_rss_mb, peak_rss_mb; "
            "a = (current_rss_mb(), peak_rss_mb()); x = np.ones(int(a[1] - a[0] + 200) * 2**20 // 8); "
            "b = (current_rss_mb(), peak_rss_mb()); del x; c = (current_rss_mb(), peak_rss_mb()); "
            "print(json.dumps([a, b, c]))")
    (rss0, peak0), (rss1, peak1), (rss2, peak2) = json.loads(
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    assert rss1 - rss0 > (peak0 - rss0) + 180 and peak1 - peak0 > 150  # the buffer is counted, in MiB
    assert rss2 < rss1 - 150 and peak2 >= peak1  # freed memory leaves the current RSS, never the peak
    assert views_memory_mb([]) == 0
