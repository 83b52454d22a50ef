"""Long streams: nothing the mapper keeps grows with the number of frames beyond a configured bound, and the soak
benchmark (benchmarks/budget/soak.py) that checks it on 20,000 frames still runs and reports a bounded run."""


import numpy as np
import pytest

import eligsir_o3d as eo3d
from eligsir_o3d.scheduling.fidelity import FidelityConfig, LoadAdaptiveFidelity
from helpers.scripts import load_script


def _soak_module():
    return load_script("benchmarks/budget/soak.py", "soak")


def test_fidelity_trace_is_bounded_and_still_spans_the_stream():
    ctrl = LoadAdaptiveFidelity(FidelityConfig(trace_max=50))
    ctrl.attach(period_s=1.0)
    for _ in range(5000):
        s = ctrl.scale()
        ctrl.observe(0.01 * s, int(640 * 480 * s * s), 0)
    updates = [d["update"] for d in ctrl.trace]
    assert 25 <= len(updates) <= 50  # bounded (5,000 decisions without the bound)
    assert np.unique(np.diff(updates)).size == 1  # evenly spaced ...
    assert updates[0] <= 5000 / 25 and updates[-1] > 5000 - 5000 / 25  # ... over the whole stream
    assert ctrl.trace[-1]["supervised_mpix"] <= ctrl.supervised_pixels / 1e6
    # a checkpoint keeps the thinned step: the restored controller keeps thinning in step with the original
    other = LoadAdaptiveFidelity(FidelityConfig(trace_max=50))
    other.load_state_dict(ctrl.state_dict())
    for c in (ctrl, other):
        for _ in range(3000):
            s = c.scale()
            c.observe(0.01 * s, int(640 * 480 * s * s), 0)
    assert other.trace == ctrl.trace and len(ctrl.trace) <= 50


def test_soak_benchmark_reports_a_bounded_run():
    soak = _soak_module()
    lines = []
    cfg = eo3d.Config()
    cfg.support.scale, cfg.growth.seed_stride = 1.0, 1  # seeds densely: tiny frames reach the cap within the run
    cfg.fidelity.trace_max = 16  # 300 updates: the Reconstructor's fidelity trace is thinned several times
    res = soak.soak(frames=300, report_every=75, resolution=(24, 18), updates=1, max_gaussians=300, max_views_=6,
                    loop=60, config=cfg, out=lines.append)
    assert res["ok"], "\n".join(lines)
    rows = res["rows"]
    assert [r["frames"] for r in rows] == [75, 150, 225, 300]
    assert all(r["gaussians"] <= 300 and r["views"] <= 6 for r in rows)
    assert rows[-1]["gaussians"] >= 0.95 * 300 and rows[-1]["views"] == 6  # it reached the caps it checks
    assert set(res["checks"]) == {"memory", "growth", "latency"}
    m = res["checks"]["memory"]
    assert m["peak_rss_mb"] <= m["budget_mb"]
    assert rows[-1]["updates"] == 300 and all(r["fidelity_trace"] <= 16 for r in rows)
    assert any("caps: max_gaussians=300 views.max_views=6" in line for line in lines)
    assert lines[-1] == "soak: OK"


def test_soak_verdict_flags_growth_after_saturation_and_latency_beyond_the_map():
    soak = _soak_module()
    caps = {"gaussians_mb": 1.0, "views_mb": 1.0, "max_gaussians": 100, "max_views": 4}

    def row(frames, rss, cpu, g=100):
        return {"frames": frames, "peak_rss_mb": rss, "rss_mb": rss, "map_mb": 0.5, "views_mb": 0.5, "gaussians": g,
                "views": 4, "latency_ms": cpu, "cpu_ms": cpu}

    flat = [row(1000, 500, 10, 50), row(2000, 501, 10), row(3000, 502, 11)]
    assert soak.verdict(flat, caps, 64, 32, 2.0)["ok"]
    leaking = [row(1000, 500, 10, 50), row(2000, 501, 10), row(3000, 600, 11)]
    v = soak.verdict(leaking, caps, 64, 32, 2.0)
    assert not v["ok"] and not v["checks"]["growth"]["ok"] and not v["checks"]["memory"]["ok"]
    slower = [row(1000, 500, 10, 50), row(2000, 501, 10), row(3000, 502, 25)]
    v = soak.verdict(slower, caps, 64, 32, 2.0)
    assert not v["ok"] and not v["checks"]["latency"]["ok"] and v["checks"]["memory"]["ok"]
    # latency that grows with the map before saturation is explained by it
    growing = [row(1000, 500, 10, 20), row(2000, 501, 40, 80)]
    assert soak.verdict(growing, caps, 64, 32, 2.0)["checks"]["latency"]["ok"]


def test_soak_rejects_a_bad_resolution():
    soak = _soak_module()
    with pytest.raises(SystemExit):
        soak.main(["synthetic", "--resolution", "64by48"])


def test_soak_kitchen_mode_samples_rss_through_the_pipeline_hook():
    """The real-time replay half of the benchmark, on a short synthetic sequence (the same pipeline as the kitchen)."""
    soak = _soak_module()
    lines = []
    res = soak.kitchen(frames=24, sample_every=5, path="synthetic", out=lines.append)
    assert res["ok"] and res["frames_released"] == 21  # 24 frames, every 8th (offset 4) held out
    assert [s["released"] for s in res["samples"]] == [5, 10, 15, 20]
    assert res["start_rss_mb"] > 0 and res["peak_before_stream_mb"] <= res["peak_mapping_mb"] <= res["peak_rss_mb"]
    assert res["peak_rss_mb"] <= res["budget_mb"] and res["updates"] > 0
    assert any(line.startswith("memory: peak RSS") and line.endswith(": ok") for line in lines)
