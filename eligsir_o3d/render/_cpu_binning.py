"""Numba kernel of the ``cpu`` renderer's tile binning: the reference's per-tile, front-to-back lists
(:func:`..projection.bin_tiles`), compressed instead of padded. Cached on disk like the other kernels."""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ..runtime.jit import jit as _jit
from ._cpu_kernels import HALF, TILE


@_jit
def bin_tiles_fill(means2d, radii, by_depth, tiles_x, tiles_y, chunks):
    """The reference's tile binning (:func:`..projection.bin_tiles`) as compressed lists.

    means2d [N, 2] float32, radii [N] int32, by_depth [V] int64: the visible Gaussians (radius > 0) front to back,
    ties in depth by index (the order of the reference's stable sorts). Returns offsets [T + 1] and flat_ids [M]
    (int64): tile t's Gaussians, front to back, are ``flat_ids[offsets[t]:offsets[t + 1]]``. The tile range of a
    Gaussian is computed with the reference's float32 operations in the same order, so the lists are identical.
    The depth order is cut into ``chunks`` consecutive parts that count and fill in parallel, each from its own
    start in every tile's list (the counts of the parts before it), so the lists do not depend on ``chunks``.
    """
    n_vis = by_depth.shape[0]
    n_tiles = tiles_x * tiles_y
    rect = np.empty((n_vis, 4), np.int64)
    counts = np.zeros((chunks, n_tiles), np.int64)
    per = (n_vis + chunks - 1) // chunks
    inv_tile = np.float32(1.0 / TILE)
    for c in prange(chunks):
        for i in range(c * per, min(n_vis, (c + 1) * per)):
            g = by_depth[i]
            r = np.float32(radii[g])
            mx = means2d[g, 0]
            my = means2d[g, 1]
            x0 = min(max(math.floor(((mx - r) + HALF) * inv_tile), 0), tiles_x)
            x1 = min(max(math.floor(((mx + r) + HALF) * inv_tile) + 1, 0), tiles_x)
            y0 = min(max(math.floor(((my - r) + HALF) * inv_tile), 0), tiles_y)
            y1 = min(max(math.floor(((my + r) + HALF) * inv_tile) + 1, 0), tiles_y)
            rect[i, 0] = x0
            rect[i, 1] = x1
            rect[i, 2] = y0
            rect[i, 3] = y1
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    counts[c, ty * tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    fill = np.empty((chunks, n_tiles), np.int64)
    for t in range(n_tiles):
        total = offsets[t]
        for c in range(chunks):
            fill[c, t] = total
            total += counts[c, t]
        offsets[t + 1] = total
    flat_ids = np.empty(offsets[-1], np.int64)
    for c in prange(chunks):
        for i in range(c * per, min(n_vis, (c + 1) * per)):
            g = by_depth[i]
            for ty in range(rect[i, 2], rect[i, 3]):
                for tx in range(rect[i, 0], rect[i, 1]):
                    t = ty * tiles_x + tx
                    flat_ids[fill[c, t]] = g
                    fill[c, t] += 1
    return offsets, flat_ids
