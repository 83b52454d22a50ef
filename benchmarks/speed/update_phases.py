"""The phases of one mapping update, timed on 1 and N threads: ``update_time.py --phases`` (this module holds its
thread helpers: the ideal loop each worker times, the phase timer its workers install, the table its driver prints).

Which part of an update holds a second core back: each phase's milliseconds per update on N threads and, in the
same rounds and process, on one thread; its speed-up; its share of the N-thread update. The phases are the
policies' methods on the worker's Reconstructor (the choice of view, the supervision sample, the render, the
regulariser, Adam, MCMC, the views' feedback) and the module-level steps of an update (the view test and the
gather of the rows in view, the loss, autograd's backward); "the rest" is the update less all of them. Read
against the ideal loop's speed-up that the table's run prints: a phase near it scales, one near 1 is serial. The
phases are means (the whole updates' table gives medians), so a view's first use (its supervision pyramid) counts:
give ``--warm`` enough updates to visit every view (``--in-view`` maps have 5 views, the others 20).

    python benchmarks/speed/update_time.py --in-view 20000 --gaussians 20000 --threads 1 2 --warm 10 --updates 10 \
        --rounds 4 --phases
"""

from __future__ import annotations

import time


def ideal_loop():
    """A compiled loop that parallelises perfectly (80 independent items of float32 exp work, ~5 ms on one thread):
    what the machine's threads deliver at a moment, to read an update's thread speed-up against."""
    import numba
    import numpy as np

    @numba.njit(parallel=True, cache=False)
    def loop(x, out, reps):
        for i in numba.prange(x.shape[0]):
            acc = np.float32(0.0)
            for r in range(reps):
                acc += np.exp(-x[i] * np.float32(r) * np.float32(1e-3))
            out[i] = acc

    x = np.random.default_rng(0).random(80 * 256).astype(np.float32)
    out = np.empty_like(x)
    loop(x, out, 1)
    return lambda: loop(x, out, 100)


def ideal_speedup(probe, threads: int) -> float:
    """Wall time of the ideal loop on one thread over its time on ``threads``, alternated 3 times (medians)."""
    import numba
    if threads == 1:
        return 1.0
    ts = {1: [], threads: []}
    for _ in range(3):
        for th in ts:
            numba.set_num_threads(th)
            t0 = time.perf_counter()
            probe()
            ts[th].append(time.perf_counter() - t0)
    numba.set_num_threads(threads)
    return sorted(ts[1])[1] / sorted(ts[threads])[1]


def _wrap(timing, obj, attr: str, name: str) -> None:
    """Time every call of ``obj.attr`` into ``timing`` under ``name`` (in this worker process only: a checkout of
    any age is timed the same way, without code of its own for it); absent or already wrapped: unchanged."""
    import functools

    fn = getattr(obj, attr, None)
    if fn is None or getattr(fn, "_stage", None) == name:
        return

    @functools.wraps(fn)
    def timed(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            timing.add(name, time.perf_counter() - t0)

    timed._stage = name
    setattr(obj, attr, timed)


def phase_timer(rec):
    """Wall seconds per phase of ``rec``'s updates (``--phases``): the policies' methods on this Reconstructor's
    instances (wrapped here, so that any checkout is timed alike), and, in this worker process only, the module-level
    steps an update calls (the view test and gather of the rows in view, the loss, autograd's backward). Returns
    the StageTimes they add to."""
    import importlib

    import torch

    from eligsir_o3d.budget.stages import StageTimes
    from eligsir_o3d.render import culling

    try:  # the module that calls the loss: where it is in this checkout
        recmod = importlib.import_module("eligsir_o3d.mapper.reconstructor")
    except ImportError:
        recmod = importlib.import_module("eligsir_o3d.reconstructor")

    timing = StageTimes()
    for path, attr, name in (("views", "select", "select view"), ("supervision", "sample", "supervision"),
                             ("renderer", "render", "render"), ("renderer", "render_training", "render"),
                             ("growth", "pre_backward", "regulariser"),
                             ("", "_adam_step", "adam"), ("growth", "post_step", "mcmc"),
                             ("views", "feedback", "feedback"), ("kernels", "select", "rows in view"),
                             ("kernels", "backward", "loss and backward"), ("kernels", "step", "step")):
        _wrap(timing, getattr(rec, path, None) if path else rec, attr, name)  # absent in a checkout: not timed
    # module-level steps (those an older checkout lacks are not timed; the view test and gather of the rows in view
    # is one classmethod, which stays one when wrapped: the class hands out the wrapper unbound)
    for obj, attr, name in ((getattr(culling, "InView", None), "select", "rows in view"),
                            (recmod, "supervision_loss", "loss"), (torch.Tensor, "backward", "backward")):
        _wrap(timing, obj, attr, name)
    return timing


def report_phases(results: dict, codes, threads) -> None:
    """Per checkout, thread count above 1 and map: each phase's ms per update on N threads and, paired, on 1
    thread in the same rounds, its speed-up and its share of the N-thread update; "the rest" is the update less
    the named phases (Python between the steps)."""
    import numpy as np

    for name, _, _ in codes:
        for th in (t for t in threads if t > 1):
            rounds = results[(name, th)]
            for gi in range(len(rounds[0])):
                rows = [r[gi] for r in rounds if r[gi]["phases"] and r[gi]["phases_1"]]
                if not rows:
                    continue
                n_up, n_up1 = sum(len(r["seconds"]) for r in rows), sum(len(r["seconds_1"]) for r in rows)
                tot = 1e3 * sum(sum(r["seconds"]) for r in rows) / n_up
                tot1 = 1e3 * sum(sum(r["seconds_1"]) for r in rows) / n_up1
                names = sorted({k for r in rows for k in r["phases"]},
                               key=lambda k: -sum(r["phases"].get(k, 0.0) for r in rows))
                ms = {k: 1e3 * sum(r["phases"].get(k, 0.0) for r in rows) / n_up for k in names}
                ms1 = {k: 1e3 * sum(r["phases_1"].get(k, 0.0) for r in rows) / n_up1 for k in names}
                ms["the rest"], ms1["the rest"] = tot - sum(ms.values()), tot1 - sum(ms1.values())
                print(f"# {name}, map of {rows[0]['gaussians']} ({int(np.median([v for r in rows for v in r['in_view']]))}"
                      f" in view): phases, ms per update on 1 / {th} thread(s) (mean of {n_up} updates each)")
                print(f"{'phase':>22} {'1 thread':>9} {str(th) + ' threads':>10} {'speed-up':>9} {'share':>6}")
                for k in names + ["the rest", None]:
                    a, b = (tot1, tot) if k is None else (ms1[k], ms[k])
                    print(f"{k or 'update':>22} {a:9.2f} {b:10.2f} {a / b if b > 0 else float('nan'):9.2f} "
                          f"{b / tot:6.1%}")
