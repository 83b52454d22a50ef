"""A spatial index over a large map's rows, so that an update's view test reads the rows near the view, not the map.

The rows are sorted along a Morton (Z-order) curve of 12.5 cm cells and cut into groups of :data:`GROUP` rows in
that order; each group keeps the box of its rows' means and their largest log scale. A view test
(:meth:`CellIndex.rows`) first tests the groups' boxes against the view (:func:`._cull_kernels.groups_hit`: a
bound that is never smaller than the row test's, so a group it rejects holds no row the row test would keep), then
runs the row test of :func:`.culling.in_view` over the rows of the groups it keeps and over the rows appended since
the index was built. The ids it returns are exactly those of the row test over the whole map, ascending (tested).

Upkeep: a group's box is recomputed from its rows' current values before the next test whenever any of its rows
changed. The map tells the index which rows changed (:meth:`.gaussians.GaussianMap.touched`: Adam's rows, the
position noise's, relocation's); rows appended after the build are tested one by one until the next rebuild; a
removal or a reload (the row ids change) rebuilds it. It is rebuilt too once the appended rows reach a quarter of
the indexed ones, or (at most every 256 tests) the rows of the groups kept exceed eight times the rows kept and half
the map (relocation scattered the groups' rows across the scene).

Below :data:`MIN_ROWS` rows the plain pass over every row is cheaper than the upkeep and the map keeps no index.
"""

from __future__ import annotations

import numpy as np
import torch

GROUP = 256  # rows per group: small enough that a group's box stays tight, large enough to test few boxes
CELL_M = 0.125  # Morton cell edge (metres): the order within a group follows cells of this size
MIN_ROWS = 200_000  # maps with fewer rows keep no index (the pass over every row takes < 1.5 ms there)


def morton_order(means: np.ndarray, cell: float = CELL_M) -> np.ndarray:
    """Row ids [N] sorted along the Z-order curve of ``cell``-sized cells (21 bits per axis; coordinates are taken
    relative to the map's minimum, so any map within 262 km fits)."""
    q = np.floor((means - means.min(0)) / cell).astype(np.int64)
    np.clip(q, 0, (1 << 21) - 1, out=q)
    code = np.zeros(means.shape[0], np.int64)
    for axis in range(3):
        v = q[:, axis]
        v = (v | (v << 32)) & 0x1F00000000FFFF
        v = (v | (v << 16)) & 0x1F0000FF0000FF
        v = (v | (v << 8)) & 0x100F00F00F00F00F
        v = (v | (v << 4)) & 0x10C30C30C30C30C3
        v = (v | (v << 2)) & 0x1249249249249249
        code |= v << axis
    return np.argsort(code, kind="stable")


class CellIndex:
    """Groups of spatially close rows of one map with their bounds; see the module docstring."""

    def __init__(self, gmap):
        self.gmap = gmap
        self.builds = 0
        self._build()

    # ---- upkeep ---------------------------------------------------------------------------------------
    def _build(self) -> None:
        means = self.gmap.params["means"].detach().numpy()
        n = means.shape[0]
        self.n = n  # rows indexed; rows n.. (appended since) are tested one by one
        self.epoch = self.gmap.rows_epoch
        self.order = morton_order(means) if n else np.zeros(0, np.int64)
        self.starts = np.minimum(np.arange(0, n + GROUP, GROUP, dtype=np.int64), n)
        if self.starts.size < 2:
            self.starts = np.zeros(2, np.int64)
        groups = self.starts.size - 1
        self.group_of = np.empty(n, np.int32)
        self.group_of[self.order] = np.arange(n, dtype=np.int64) // GROUP
        self.boxes = np.empty((groups, 7), np.float32)
        self.dirty = np.ones(groups, np.bool_)
        self.builds += 1
        self.tests = 0

    def mark(self, rows: torch.Tensor | None) -> None:
        """Rows whose means or scales changed (None: every row): their groups' boxes are recomputed before use."""
        if rows is None:
            self.dirty[:] = True
            return
        from ._cull_kernels import mark_groups

        r = rows.detach().cpu().numpy() if isinstance(rows, torch.Tensor) else np.asarray(rows)
        mark_groups(self.group_of, r.astype(np.int64, copy=False), self.n, self.dirty)

    def _stale(self) -> bool:
        n = len(self.gmap)
        return self.gmap.rows_epoch != self.epoch or n < self.n or (n - self.n) * 4 > max(self.n, 4 * GROUP)

    # ---- the view test --------------------------------------------------------------------------------
    def rows(self, V: np.ndarray, cam: np.ndarray) -> np.ndarray:
        """int64 ids, ascending, of the rows the row test keeps for world-to-camera ``V`` and ``cam``
        (:func:`.culling.camera_bounds`)."""
        from ..runtime.jit import rows_threads
        from ._cull_kernels import group_boxes, groups_hit, listed_rows, frustum_rows

        if self._stale():
            self._build()
        p = self.gmap.params
        means = p["means"].detach().contiguous().numpy()
        log_scales = p["scales"].detach().contiguous().numpy()
        with rows_threads(self.n, "cell_index"):
            dirty = np.flatnonzero(self.dirty)
            if dirty.size:
                group_boxes(means, log_scales, self.order, self.starts, dirty, self.boxes)
                self.dirty[dirty] = False
            keep = groups_hit(self.boxes, V, cam)
            found, tested = listed_rows(means, log_scales, self.order, self.starts, keep, V, cam)
        tail = len(self.gmap) - self.n
        if tail:
            with rows_threads(tail, "frustum_rows"):
                extra = frustum_rows(means[self.n:], log_scales[self.n:], V, cam) + self.n
            found = np.concatenate([found, extra])
        found.sort()
        self.tests += 1
        if self.tests >= 256 and tested > GROUP * 8 + 8 * found.size and tested * 2 > self.n:
            self.epoch = -1  # the groups have spread out (relocation): rebuild before the next test
        return found
