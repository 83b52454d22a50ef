"""The measured choice of one numba thread or all for per-Gaussian kernels between the two limits
(runtime.row_threads, runtime.jit.rows_threads): it tries both ways, keeps the faster, looks at the other now and
then, follows a change of load, and never changes a result (test_numba_thread_bits covers the bits)."""

import numba
import pytest

from eligsir_o3d.runtime import jit
from eligsir_o3d.runtime.row_threads import RowThreads
from eligsir_o3d.runtime.threads import PARALLEL_FLOOR_ROWS


def _run(chooser, key, rows, calls, per_row):
    """``calls`` calls of kernel ``key`` timed at ``per_row(parallel)`` seconds a row: the ways they took."""
    ways = []
    for _ in range(calls):
        parallel = chooser.choose(key, rows)
        chooser.record(key, rows, parallel, per_row(parallel) * rows)
        ways.append(parallel)
    return ways


def test_it_tries_both_ways_then_keeps_the_faster_and_explores_the_other():
    rt = RowThreads(explore=8)
    ways = _run(rt, "step", 4000, 34, lambda p: 20e-9 if p else 50e-9)
    assert ways[:2] == [False, True]  # one thread first, then all
    later = ways[2:]
    assert later.count(False) == sum(1 for n in range(2, 34) if n % 8 == 0)  # the other way every 8th call
    assert all(later[i] for i in range(len(later)) if (i + 2) % 8)
    assert rt.report() == {"one": 1 + later.count(False), "all": 1 + later.count(True)}


def test_it_follows_a_change_of_load():
    rt = RowThreads(explore=4, decay=0.5)
    busy = {"on": False}
    per_row = lambda p: (90e-9 if busy["on"] else 20e-9) if p else 40e-9  # noqa: E731
    assert _run(rt, "project", 3000, 12, per_row)[-1] is True
    busy["on"] = True  # another process takes the second core: parallel regions wait for it
    ways = _run(rt, "project", 3000, 40, per_row)
    assert ways[-3:] == [False, False, False]
    busy["on"] = False
    assert _run(rt, "project", 3000, 40, per_row)[-3:] == [True, True, True]


def test_kernels_and_size_classes_are_measured_apart():
    rt = RowThreads()
    _run(rt, "step", 4000, 6, lambda p: 10e-9 if p else 50e-9)
    _run(rt, "frustum", 4000, 6, lambda p: 90e-9 if p else 20e-9)
    _run(rt, "step", 1500, 6, lambda p: 90e-9 if p else 20e-9)
    assert rt.choose("step", 4000) is True
    assert rt.choose("frustum", 4000) is False
    assert rt.choose("step", 1500) is False
    assert set(rt.classes) == {("step", (4000).bit_length()), ("frustum", (4000).bit_length()),
                               ("step", (1500).bit_length())}


def test_one_stalled_call_does_not_flip_the_choice():
    rt = RowThreads(explore=1000, decay=0.25, outlier=4.0)
    _run(rt, "step", 4000, 10, lambda p: 20e-9 if p else 40e-9)
    rt.record("step", 4000, True, 1.0)  # a lost time slice: 250 us a row
    assert rt.classes[("step", (4000).bit_length())].per_row[1] < 40e-9
    assert rt.choose("step", 4000) is True


@pytest.fixture
def two_numba_threads():
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    old = numba.get_num_threads()
    numba.set_num_threads(2)
    yield
    numba.set_num_threads(old)


def test_rows_threads_sets_the_threads_it_chose_and_restores_them(two_numba_threads, monkeypatch):
    rt = RowThreads()
    monkeypatch.setattr(jit, "ROW_THREADS", rt)
    with jit.rows_threads(PARALLEL_FLOOR_ROWS - 1, "k") as parallel:  # below the floor: one thread, unmeasured
        assert parallel is False and numba.get_num_threads() == 1
    assert numba.get_num_threads() == 2
    with jit.rows_threads(jit.ROWS_LIMIT, "k") as parallel:  # from the limit: all threads, unmeasured
        assert parallel is True and numba.get_num_threads() == 2
    assert rt.classes == {}
    rows = (PARALLEL_FLOOR_ROWS + jit.ROWS_LIMIT) // 2
    seen = []
    for _ in range(3):
        with jit.rows_threads(rows, "k") as parallel:
            seen.append((parallel, numba.get_num_threads()))
        assert numba.get_num_threads() == 2
    assert seen[:2] == [(False, 1), (True, 2)]
    c = rt.classes[("k", rows.bit_length())]
    assert c.calls == 3 and None not in c.per_row
    with pytest.raises(RuntimeError), jit.rows_threads(rows, "k"):
        raise RuntimeError("a kernel that fails")
    assert numba.get_num_threads() == 2
