"""Issue 31 item 13: a calibrated cost model records the conditions it was taken under; a fit taken on a busy
machine, an old one or one of another kernel is not reused; eligsir calibrate shows it and --force retakes it.
The machine's real load is never a test input: readings are injected (conditions.READERS)."""

import json

import pytest
from typer.testing import CliRunner

from eligsir_o3d.budget import calibrate as cal
from eligsir_o3d.budget import conditions
from eligsir_o3d.budget.cost import CostModel

DAY = 86400.0


@pytest.fixture
def machine(tmp_path, monkeypatch):
    """A quiet 2-CPU machine on kernel k1 at t = 100 days, a cache folder of its own, and a counted calibrate."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    state = {"load": 0.2, "spread": 1.05, "cpus": 2, "kernel": "k1", "now": 100 * DAY, "calls": 0}
    for k in ("load", "spread", "cpus", "kernel", "now"):
        monkeypatch.setitem(conditions.READERS, k, lambda k=k: state[k])

    def fake_calibrate(rec, frames=None, **kw):
        state["calls"] += 1
        return CostModel(), {"frames": 0}

    monkeypatch.setattr(cal, "calibrate", fake_calibrate)
    return state


class _Rec:
    device = "cpu"

    class config:
        renderer = "torch"


def test_a_quiet_fit_is_recorded_and_reused(machine):
    m, info = cal.cached_cost_model(_Rec())
    assert info["fresh"] and info["conditions"]["load_1m"] == 0.2 and info["conditions"]["busy"] is None
    saved = json.loads(open(info["cache"]).read())
    assert saved["conditions"]["kernel"] == "k1" and saved["conditions"]["taken"] == 100 * DAY
    _, again = cal.cached_cost_model(_Rec())
    assert not again["fresh"] and machine["calls"] == 1


@pytest.mark.parametrize("reading, value, said", [("load", 15.0, "load average 15.0 on 2"),
                                                  ("spread", 3.0, "varied 3.0x")])
def test_a_busy_fit_is_used_once_and_retaken(machine, caplog, reading, value, said):
    machine[reading] = value
    _, info = cal.cached_cost_model(_Rec())
    assert said in info["conditions"]["busy"] and "calibrated on a busy machine" in caplog.text
    machine[reading] = 0.2 if reading == "load" else 1.0
    _, info = cal.cached_cost_model(_Rec())
    assert info["fresh"] and machine["calls"] == 2 and "taken on a busy machine" in caplog.text


@pytest.mark.parametrize("change, said", [(("now", 140 * DAY), "40 days old"), (("kernel", "k2"), "kernel k1")])
def test_a_stale_fit_is_retaken(machine, caplog, change, said):
    cal.cached_cost_model(_Rec())
    machine[change[0]] = change[1]
    _, info = cal.cached_cost_model(_Rec())
    assert info["fresh"] and machine["calls"] == 2 and said in caplog.text


def test_an_old_cache_file_without_conditions_is_retaken(machine):
    _, info = cal.cached_cost_model(_Rec())
    data = json.loads(open(info["cache"]).read())
    del data["conditions"]
    open(info["cache"], "w").write(json.dumps(data))
    _, info = cal.cached_cost_model(_Rec())
    assert info["fresh"]


def test_eligsir_calibrate_shows_and_forces(machine):
    from eligsir_o3d.cli.app import app

    r = CliRunner().invoke(app, ["calibrate", "--renderer", "torch"])
    assert r.exit_code == 0 and "no cost model calibrated yet" in r.output, r.output
    machine["load"] = 9.0
    r = CliRunner().invoke(app, ["calibrate", "--renderer", "torch", "--force"])
    assert r.exit_code == 0 and machine["calls"] == 1, r.output
    assert "load average 9.00 on 2 CPU(s)" in r.output and "NOT reused (it was taken on a busy machine" in r.output
