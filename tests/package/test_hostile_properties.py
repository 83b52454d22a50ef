"""Property-based suite over each phone reader's metadata parser and each numeric run option: any mutation of a
valid Record3D metadata, Polycam camera JSON, Stray odometry CSV or option value ends in a result (a Sequence's
parts, a typed option) or in one ``ValueError`` line naming the file and the field. Never another exception, never
a hang: every case runs under :data:`CASE_TIMEOUT_S` (SIGALRM).

The run uses a fixed seed (:data:`SEED`, printed and recorded as the test's ``hypothesis_seed`` property);
``ELIGSIR_PROPERTY_SEED=N`` and ``ELIGSIR_PROPERTY_EXAMPLES=N`` run other or more cases.
"""

from __future__ import annotations

import json
import math
import os
import signal
from contextlib import contextmanager

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, seed, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SEED = int(os.environ.get("ELIGSIR_PROPERTY_SEED", "7"))
EXAMPLES = int(os.environ.get("ELIGSIR_PROPERTY_EXAMPLES", "60"))
CASE_TIMEOUT_S = 5
PROPS = settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(autouse=True)
def _log_seed(record_property):
    print(f"hypothesis seed {SEED}, {EXAMPLES} examples per property")
    record_property("hypothesis_seed", SEED)


@contextmanager
def _bounded():
    """Fail the case (instead of hanging the suite) when it runs past CASE_TIMEOUT_S."""
    def expired(signum, frame):
        raise TimeoutError(f"case ran past {CASE_TIMEOUT_S} s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.alarm(CASE_TIMEOUT_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _refused(e: BaseException, where: str) -> None:
    msg = str(e)
    assert isinstance(e, ValueError) and not isinstance(e, TimeoutError), repr(e)
    assert "\n" not in msg and where in msg, msg


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(min_value=-(10 ** 30), max_value=10 ** 30)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12)


def _mutated(base: dict, keys: list[str]):
    """A strategy of ``base`` with one key replaced, dropped or added, or the whole document replaced."""
    replace = st.tuples(st.sampled_from(keys), JSON_VALUES).map(lambda kv: {**base, kv[0]: kv[1]})
    drop = st.sampled_from(keys).map(lambda k: {x: v for x, v in base.items() if x != k})
    return st.one_of(replace, replace, drop, JSON_VALUES)


R3D = {"w": 64, "h": 48, "K": [50.0, 0, 0, 0, 50.0, 0, 32.0, 24.0, 1.0], "dw": 16, "dh": 12, "fps": 30,
       "poses": [[0, 0, 0, 1, 0, 0, 0], [0, 0, 0, 1, 0.1, 0, 0], [0, 0, 0, 1, 0.2, 0, 0]],
       "frameTimestamps": [0.0, 0.1, 0.2], "perFrameIntrinsicCoeffs": [[50, 50, 32, 24]] * 3}


@seed(SEED)
@PROPS
@given(_mutated(R3D, list(R3D)))
def test_record3d_metadata_parses_or_names_the_field(meta):
    from eligsir_o3d.datasets.record3d import (color_camera, frame_timestamps, parse_metadata,
                                               poses_from_metadata)

    where = "cap.r3d:metadata"
    with _bounded():
        try:
            m = parse_metadata(json.dumps(meta).encode(), where)
            cam = color_camera(m, where)
            poses = poses_from_metadata(m)
            keep, stamps, _ = frame_timestamps(m, [0, 1, 2], [0, 1, 2], None, str)
        except Exception as e:  # noqa: BLE001 - the property: a ValueError line naming the file, nothing else
            _refused(e, where)
            return
    assert cam.width > 0 and cam.fx > 0 and math.isfinite(cam.cx)
    assert len(poses) == len(m["poses"]) and all(math.isfinite(t) for t in stamps)
    assert all(b > a for a, b in zip(stamps, stamps[1:])) and len(keep) == len(stamps)


POLY = {"fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, "width": 64, "height": 48, "timestamp": 1000,
        **{f"t_{r}{c}": float(r == c) for r in range(3) for c in range(4)}}


@seed(SEED)
@PROPS
@given(_mutated(POLY, list(POLY)))
def test_polycam_camera_parses_or_names_the_field(tmp_path_factory, data):
    from eligsir_o3d.datasets.polycam import _read_camera

    path = tmp_path_factory.mktemp("poly") / "1000.json"
    path.write_text(json.dumps(data))
    with _bounded():
        try:
            cam, T, stamp = _read_camera(path)
        except Exception as e:  # noqa: BLE001
            _refused(e, str(path))
            return
    assert cam.width > 0 and cam.fx > 0 and math.isfinite(cam.cx)
    assert T is None or T.shape == (4, 4)


CELLS = st.sampled_from(["nan", "inf", "-inf", "", "abc", "1e400", "9" * 40, "0x10", "-1", "0.5", "3"])
ODO = ["timestamp, frame, x, y, z, qx, qy, qz, qw"] + [f"{0.1 * k}, {k}, 0, 0, {0.1 * k}, 0, 0, 0, 1"
                                                        for k in range(4)]


@seed(SEED)
@PROPS
@given(st.lists(st.tuples(st.integers(0, 4), st.integers(0, 8), CELLS), min_size=1, max_size=4),
       st.sampled_from(["none", "drop-last", "duplicate", "no-header"]))
def test_stray_odometry_parses_or_names_the_line(tmp_path_factory, edits, shape):
    from eligsir_o3d.datasets.phone_meta import usable_stamps
    from eligsir_o3d.datasets.stray import _rows_by_frame, read_odometry

    lines = [ln.split(", ") for ln in ODO]
    for row, col, value in edits:
        lines[row][col] = value
    text = [", ".join(ln) for ln in lines]
    text = {"none": text, "drop-last": text[:-1], "duplicate": text + text[-1:], "no-header": text[1:]}[shape]
    path = tmp_path_factory.mktemp("stray") / "odometry.csv"
    path.write_text("\n".join(text) + "\n")
    with _bounded():
        try:
            rows = read_odometry(path)
            by_frame = _rows_by_frame(path, rows, [0, 1, 2])
            ok, _ = usable_stamps([by_frame[n].get("timestamp", n / 60) for n in (0, 1, 2)], ["a", "b", "c"])
        except Exception as e:  # noqa: BLE001
            _refused(e, str(path))
            return
    assert all(math.isfinite(r["frame"]) for r in rows if "frame" in r) and len(ok) == 3


OPTION_VALUES = (st.none() | st.booleans() | st.integers(-(10 ** 25), 10 ** 25)
                 | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8))


@seed(SEED)
@PROPS
@given(st.sampled_from(sorted(__import__("eligsir_o3d.run.option_table", fromlist=["OPTIONS"]).OPTIONS)),
       OPTION_VALUES)
def test_every_numeric_option_is_in_range_or_refused_naming_it(name, value):
    from eligsir_o3d.run.option_table import OPTIONS, check_option

    opt = OPTIONS[name]
    with _bounded():
        try:
            got = check_option(name, value)
        except Exception as e:  # noqa: BLE001
            _refused(e, opt.flag(name))
            return
    if got is None:
        assert opt.none_ok and value is None
        return
    assert isinstance(got, opt.kind) and math.isfinite(got) and got <= opt.high
    assert got > opt.low if opt.low_open else got >= opt.low


@seed(SEED)
@PROPS
@given(st.sampled_from(["seed", "depth_max", "clock.speed", "clock.updates_per_frame", "max_gaussians",
                        "clock.cost_feedback", "views.active_size"]), OPTION_VALUES)
def test_config_values_resolve_or_are_refused_naming_the_key(key, value):
    from eligsir_o3d import Config
    from eligsir_o3d.config.checks import check_values

    d = Config().to_dict()
    *path, last = key.split(".")
    node = d
    for p in path:
        node = node[p]
    node[last] = value
    with _bounded():
        try:
            check_values(Config.from_dict(d, "config.json"))
        except Exception as e:  # noqa: BLE001
            _refused(e, key.split(".")[-1])
