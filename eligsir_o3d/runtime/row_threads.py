"""One numba thread or all of them for a per-Gaussian kernel over a few thousand rows: whichever has lately done a
row of that kernel faster, on this machine, now.

A second thread pays on such a kernel while the second core is free and loses while another process keeps it
busy (each parallel region then waits for its worker's time slice, and a region of a few thousand rows is short).
Neither holds for a whole run, nor for every machine, so the choice is measured rather than fixed: per kernel
(a caller's key) and size class (rows within a factor of two), each way's seconds per row are an exponential
average of its calls. A call takes the faster way; every ``explore``-th call of a class takes the other one, so
that a change of load shows. The caller (:func:`.jit.rows_threads`) asks only between the limits of
:mod:`.threads`: fewer rows always run on one thread, more on all. Both ways give the same bits (the kernels
write disjoint outputs), so the choice changes speed only.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class _Class:
    calls: int = 0
    per_row: list = field(default_factory=lambda: [None, None])  # seconds per row: [one thread, all threads]


class RowThreads:
    """The choice above, with its state: per (key, size class) the calls so far and each way's average."""

    def __init__(self, explore: int = 16, decay: float = 0.25, outlier: float = 4.0):
        """``decay``: the weight of a new call in its way's average; a call slower than ``outlier`` times that
        average (a time slice lost to another process, a page fault) counts as ``outlier`` times it."""
        self.explore, self.decay, self.outlier = explore, decay, outlier
        self.classes: dict[tuple, _Class] = {}
        self.counts = {"one": 0, "all": 0}

    def choose(self, key: str, rows: int) -> bool:
        """True: run this call of kernel ``key`` over ``rows`` rows on all of numba's threads; False: on one."""
        c = self.classes.setdefault((key, rows.bit_length()), _Class())
        n = c.calls
        c.calls += 1
        one, every = c.per_row
        if one is None or every is None:  # the first calls: one way, then the other
            parallel = one is not None
        else:
            parallel = every < one
            if n % self.explore == 0:
                parallel = not parallel
        self.counts["all" if parallel else "one"] += 1
        return parallel

    def record(self, key: str, rows: int, parallel: bool, seconds: float) -> None:
        """What a call that :meth:`choose` decided took."""
        c = self.classes.get((key, rows.bit_length()))
        if c is None:
            return
        x = seconds / rows
        old = c.per_row[int(parallel)]
        if old is None:
            c.per_row[int(parallel)] = x
            return
        c.per_row[int(parallel)] = old + self.decay * (min(x, self.outlier * old) - old)

    def report(self) -> dict:
        """Calls that ran on one thread and on all, for metrics.json."""
        return dict(self.counts)
