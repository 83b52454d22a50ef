"""benchmarks/speed/update_profile.py, the GPU check's profile, runs on the CPU too: it counts the update's torch
operators and times the host, per admitted frame and with a map grown to N Gaussians in view."""

import json

from helpers.scripts import load_script


def test_profile_reports_every_figure_on_the_cpu(tmp_path, capsys):
    tool = load_script("benchmarks/speed/update_profile.py")
    out = tmp_path / "p.json"
    assert tool.main(["--device", "cpu", "--frames", "3", "--updates", "2", "--frames-timed", "1",
                      "--in-view", "600", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["kernels"] == "numba" and rep["profile"]["aten_ops"] > 0 and rep["profile"]["launches"] == 0
    assert rep["host_ms"] > 0 and rep["frame_ms"] > 0
    (grown,) = rep["maps"]
    assert grown["gaussians"] == 600 and grown["in_view"] > 300 and grown["ms_per_update"] > 0
