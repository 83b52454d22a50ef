"""Scratch arrays that outlive one kernel call and are reused once nothing refers to them.

The ``cpu`` renderer's forward kernel fills per-render tables (the gathered tiles) that its backward kernel reads
later, so they cannot be the kernel's own short-lived buffers. A fresh array of a few megabytes costs its page
faults on first touch, every render: 4-6 % of a 1/4-scale update at 100k Gaussians (in-process alternation, 1 and 2
threads; the faults of two threads also contend in the kernel). :class:`ScratchPool` keeps a few sets of arrays and
hands out views of a set that no earlier view still holds: a set is free when its arrays' reference counts are back
to the pool's own (numpy views refer to the array that owns the memory), so a render kept for a later backward, or
two renders in flight, never share a table. Sets above ``max_bytes`` are not kept (a huge full-resolution render
allocates its own and gives the memory back).
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np


class ScratchPool:
    """Reusable sets of 1-D arrays of fixed dtypes, handed out as views of the requested shapes."""

    def __init__(self, dtypes: tuple, keep: int = 2, max_bytes: int = 256 << 20):
        self.dtypes = tuple(np.dtype(d) for d in dtypes)
        self.keep = keep
        self.max_bytes = max_bytes
        self.sets: list[list[np.ndarray]] = []
        self._lock = threading.Lock()
        self._own_refs = None  # an owner's reference count while only the pool holds it

    def take(self, *shapes: tuple) -> tuple:
        """Views of the given shapes (one per dtype) on a free set, grown (by a quarter more) when too small."""
        sizes = [math.prod(s) for s in shapes]
        if sum(n * d.itemsize for n, d in zip(sizes, self.dtypes)) > self.max_bytes:
            return tuple(np.empty(s, d) for s, d in zip(shapes, self.dtypes))  # not kept
        with self._lock:
            if self._own_refs is None:
                probe = [np.empty(1)]
                self._own_refs = sys.getrefcount(probe[0])
            free = [i for i in range(len(self.sets))
                    if all(sys.getrefcount(self.sets[i][j]) == self._own_refs for j in range(len(self.dtypes)))]
            if free and all(a.size >= n for a, n in zip(self.sets[free[0]], sizes)):
                arrays = self.sets[free[0]]
            else:
                arrays = [np.empty(n + n // 4, d) for n, d in zip(sizes, self.dtypes)]
                if free:
                    self.sets[free[0]] = arrays  # a free set too small: replaced by a larger one
                elif len(self.sets) < self.keep:
                    self.sets.append(arrays)
            return tuple(a[:n].reshape(s) for a, n, s in zip(arrays, sizes, shapes))
