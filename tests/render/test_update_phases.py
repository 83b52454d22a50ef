"""benchmarks/speed/update_time.py --phases on the kitchen: every timed update of each worker is split into its
phases (the view test, render, loss, backward, Adam, MCMC, ...), paired with the same updates on one thread, and the
named phases with "the rest" add up to the whole update."""

import re
import subprocess
import sys

import pytest

from helpers import SEVEN
from helpers.scripts import ROOT, load_script

needs_kitchen = pytest.mark.skipif(not SEVEN.is_dir(), reason="needs ../shared/data/7scenes_redkitchen_jpg1000")


@needs_kitchen
def test_phases_add_up_to_the_update(tmp_path):
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks/speed/update_time.py"), "--gaussians", "400", "--in-view", "400",
         "--threads", "1", "2", "--rounds", "1", "--updates", "3", "--warm", "2", "--phases",
         "--json", str(tmp_path / "t.json")],
        capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    head = next(i for i, line in enumerate(lines) if "phases, ms per update on 1 / 2 thread(s)" in line)
    rows = {}
    for line in lines[head + 2:]:
        m = re.match(r"\s*(.+?)\s+([-\d.]+)\s+([-\d.]+)\s+([-\d.na]+)\s+([-\d.]+)%$", line)
        if not m:
            break
        rows[m.group(1)] = (float(m.group(2)), float(m.group(3)))
    for phase in ("render", "loss", "backward", "step", "mcmc", "feedback", "select view", "rows in view",
                  "the rest", "update"):
        assert phase in rows, (phase, list(rows))
    named = [k for k in rows if k != "update"]
    for col in (0, 1):  # the phases and the rest make up the update (the rest is what is left: exact)
        assert sum(rows[k][col] for k in named) == pytest.approx(rows["update"][col], abs=0.02 * len(named))
        assert all(rows[k][col] >= 0 for k in named if k != "the rest")
    assert rows["render"][1] > 0 and rows["backward"][1] > 0


def test_report_phases_without_phase_times_prints_nothing(capsys):
    tool = load_script("benchmarks/speed/update_phases.py")
    row = {"gaussians": 10, "seconds": [0.01], "seconds_1": [0.02], "in_view": [10], "phases": None,
           "phases_1": None}
    tool.report_phases({("this", 2): [[row]]}, [("this", "=", ".")], [1, 2])
    assert capsys.readouterr().out == ""
