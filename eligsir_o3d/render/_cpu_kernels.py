"""Numba kernels of the ``cpu`` renderer, shared part: per-Gaussian culling bounds, tile gathering, the conic/alpha
evaluation (its exp is :func:`..runtime.fmath.exp_neg`) that the compositing kernels (:mod:`._cpu_forward`, :mod:`._cpu_backward`) inline, and the choice
of their pixel-block shape (the tile binning is :mod:`._cpu_binning`).

The math is the reference's (``torch_backend.TorchRenderer._tiles``) written per pixel, in float32, in the same
order of operations: ``sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy`` with ``(dx, dy) = pixel - mean``, Gaussians with
``sigma < 0`` or ``alpha < 1/255`` are skipped, ``alpha = min(0.999, o exp(-sigma))``, and a pixel stops before the
Gaussian whose blending would take its transmittance to ``<= 1e-4``. The backward pass follows gsplat's
``rasterize_to_pixels`` backward: it starts from the stored final transmittance and the number of Gaussians the
forward pass walked through, and recovers each Gaussian's transmittance by dividing by ``1 - alpha``.

Work: pixels run in blocks (4x4, :data:`BLOCKS`), and a block walks only the part of its tile's list that can reach
it: each tile's list is culled per block by the bounding box of the ellipse where ``o exp(-sigma) >= 1/255``
(conservatively, so the result is the same as walking the whole list; on a real scene this cuts the walk from ~540
to ~80 Gaussians per pixel at 160x120). The forward kernel gathers each tile's Gaussians and block lists into tables
(:func:`gather_shapes`) that the backward kernel reads, so a training render gathers once (the tables are reused
from render to render: :mod:`.scratch`). The pixels of a block are processed together without branches, in float32
only (int64 or bool lanes would narrow LLVM's vectors; conditional stores become masked stores, slow on AVX2), which
LLVM turns into SIMD code at the target's width: one AVX-512 register, two AVX2 ones; exp is a branch-free
polynomial within 2 ulp of float32 exp (the reference's exp differs from it by rounding only, so images agree to
~1e-6). No fast-math: every target computes the same bits (a map built with AVX2 kernels equals the AVX-512 one).

Parallelism: a few tasks per thread (``prange`` over :func:`task_slots`, taken one at a time so that the cores share
uneven work dynamically), each running every slots-th tile of the heaviest-first order with its pixel-block scratch
allocated once; nothing shared is sliced inside the loop (a view's reference count is updated atomically). Tiles
never write to the same memory: the backward pass writes one gradient row per (tile, Gaussian) intersection and
sums the rows per Gaussian in one serial pass after the tiles, so no atomics are needed.

Compilation is lazy (first call) and cached on disk (``cache=True``), keyed by numba on the CPU name and features it
compiles for (``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``, else the host): numba writes next to this file when the
package folder is writable, else to ``$NUMBA_CACHE_DIR`` or the user cache folder; where none is writable the
kernels still work, compiled once per process.
"""

from __future__ import annotations

import math
import zlib

import numba
import numpy as np
from numba import prange

from ..runtime.fmath import exp_neg
from ..runtime.jit import jit as _jit
from ..runtime.jit import jit_serial as _jit_serial

TILE = 16
ALPHA_MAX = np.float32(0.999)
ALPHA_MIN = np.float32(1.0 / 255.0)
T_MIN = np.float32(1e-4)
HALF = np.float32(0.5)
ONE = np.float32(1.0)
ZERO = np.float32(0.0)

# numba's disk cache checks only the source file of the cached function itself; the compositing kernels (in
# _cpu_forward.py / _cpu_backward.py) inline the helpers of this file, so they carry this file's checksum as a
# closure constant, which numba hashes into their cache key: an edit here recompiles them.
with open(__file__, "rb") as _f:
    SOURCE_CRC = zlib.crc32(_f.read())


@numba.njit(inline="always", fastmath=False)
def conic_sigma(x, y, mx, my, ca, cb, cc):
    """(dx, dy, sigma) of one Gaussian at one pixel centre: ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``."""
    dx = x - mx
    dy = y - my
    return dx, dy, HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy


@numba.njit(inline="always", fastmath=False)
def reaches(x, y, mx, my, ca, cb, cc, smax):
    """Whether the Gaussian can pass the kernels' tests at this pixel: ``0 <= sigma <= smax`` (the sigma bound of
    :func:`cull_bounds`; alpha >= 1/255 needs it). Same sigma as :func:`conic_alpha`, bit for bit, so a block whose
    pixels all fail it can skip the Gaussian without changing any result."""
    _, _, sigma = conic_sigma(x, y, mx, my, ca, cb, cc)
    return (sigma >= ZERO) & (sigma <= smax)


@numba.njit(inline="always", fastmath=False)
def conic_alpha(x, y, mx, my, ca, cb, cc, o):
    """One Gaussian at one pixel centre, as the reference computes it: (dx, dy, sigma, exp(-sigma), o exp(-sigma),
    alpha = min(0.999, o exp(-sigma))). Shared by the forward and backward kernels, so both see the same alpha."""
    dx, dy, sigma = conic_sigma(x, y, mx, my, ca, cb, cc)
    vis = exp_neg(sigma)
    o_vis = o * vis
    return dx, dy, sigma, vis, o_vis, min(ALPHA_MAX, o_vis)


@_jit
def cull_bounds(conics, opacities, out):
    """Per Gaussian: out[g] = (sigma bound, x half-width, y half-width) of the region it can reach.

    A Gaussian contributes to a pixel only if ``o exp(-sigma) >= 1/255``, i.e. ``sigma <= log(255 o)``; the bound
    keeps a margin of 1e-3 above that (float32 exp and products err by ~1e-7; -1 where ``o < 1/255``: never). The
    half-widths bound the ellipse at that level, widened for the float32 rounding of sigma in the kernels, which
    grows with the conic's condition (at most ~1e-6 * kappa * sigma with kappa = (a + c)^2 / det: ~4 for round
    Gaussians, 1e5 for 300:1 needles), and by 1e-3 px; -1 = no box (degenerate conic or NaN: never culled).
    Culling is conservative, so it changes no result.
    """
    for g in prange(opacities.shape[0]):
        o = np.float64(opacities[g])
        out[g, 1] = -1.0
        out[g, 2] = -1.0
        if o != o:  # NaN: leave it to the per-pixel tests
            out[g, 0] = np.inf
            continue
        if o * 255.0 < 1.0:
            out[g, 0] = -1.0
            continue
        smax = math.log(o * 255.0) + 1e-3
        out[g, 0] = smax
        a, b, c = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        det = a * c - b * b
        if det > 0.0 and a > 0.0:
            s_box = smax * (1.0 + 1e-3 + 2e-6 * (a + c) * (a + c) / det)
            out[g, 1] = math.sqrt(2.0 * s_box * c / det) + 1e-3
            out[g, 2] = math.sqrt(2.0 * s_box * a / det) + 1e-3


PAR = 11  # per tile intersection in the gathered table: mean x, mean y, conic a, b, c, opacity, sigma bound, features


def gather_shapes(m: int, n_tiles: int, block_pixels: int = 16) -> tuple:
    """Shapes of the tables :func:`gather_tile` fills over a render with ``m`` intersections and ``n_tiles`` tiles:
    par [m, PAR] float32, sub [blocks * m] int32, sub_n [n_tiles, blocks] int64 (blocks = 256 / block pixels).

    The forward kernel fills them and the backward kernel reads them, so a training render gathers each tile once.
    ``sub`` has room for every Gaussian of a tile in every block of it; only the lists' entries are written, so the
    pages that no list reaches cost address space, not memory."""
    blocks = TILE * TILE // block_pixels
    return (m, PAR), (blocks * m,), (n_tiles, blocks)


GATHER_DTYPES = (np.float32, np.int32, np.int64)
# columns of the backward kernel's gradient row per intersection (v_isect): its 10 channels padded to one 16-float
# vector, so that a block's pixel sums are added to the row in one vector operation
ISECT_COLS = 16


def gather_buffers(m: int, n_tiles: int, block_pixels: int = 16) -> tuple:
    """Fresh (empty) tables of :func:`gather_shapes`."""
    return tuple(np.empty(s, d) for s, d in zip(gather_shapes(m, n_tiles, block_pixels), GATHER_DTYPES))


@_jit_serial
def gather_tile(means2d, conics, opacities, feats, bounds, flat_ids, s, n, x0, y0, bw, bh, par, sub, sub_n, t):
    """Copy tile Gaussians ``flat_ids[s:s + n]`` into rows ``s:s + n`` of par and cull them per block of bw x bh pixels.

    par [M, PAR] rows: mean x, mean y, conic a, b, c, opacity, sigma bound, the 4 features. Per block b (row-major,
    (TILE / bw) x (TILE / bh) of them), the depth-ordered tile-local indices (0..n-1) of the Gaussians whose box
    (:func:`cull_bounds`) reaches it: ``sub[blocks * s + b * n:][:sub_n[t, b]]``, t the tile's row of the table
    (:func:`gather_shapes`). The tables are indexed, never sliced: a view of an array that every thread shares
    updates its reference count atomically, and those shared counters cost the parallel kernels their scaling.
    """
    nbx = TILE // bw
    nby = TILE // bh
    base = nbx * nby * s
    for j in range(nbx * nby):
        sub_n[t, j] = 0
    for k in range(n):
        g = flat_ids[s + k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        par[s + k, 0] = mx
        par[s + k, 1] = my
        par[s + k, 2] = conics[g, 0]
        par[s + k, 3] = conics[g, 1]
        par[s + k, 4] = conics[g, 2]
        par[s + k, 5] = opacities[g]
        par[s + k, 6] = bounds[g, 0]
        for f in range(4):
            par[s + k, 7 + f] = feats[g, f]
        if bounds[g, 0] < 0.0:
            continue
        rx = np.float64(bounds[g, 1])
        ry = np.float64(bounds[g, 2])
        sx0, sx1, sy0, sy1 = 0, nbx - 1, 0, nby - 1
        if rx >= 0.0:
            # block (i, j) spans pixel centres x0 + bw i .. x0 + bw i + bw - 1 and y0 + bh j .. y0 + bh j + bh - 1
            lo_x = (np.float64(mx) - rx - x0) / bw
            hi_x = (np.float64(mx) + rx - x0) / bw
            lo_y = (np.float64(my) - ry - y0) / bh
            hi_y = (np.float64(my) + ry - y0) / bh
            sx0 = max(0, int(math.ceil(lo_x - (bw - 1.0) / bw))) if lo_x > -1.0 else 0
            sx1 = min(nbx - 1, int(math.floor(hi_x))) if hi_x < nbx else nbx - 1
            sy0 = max(0, int(math.ceil(lo_y - (bh - 1.0) / bh))) if lo_y > -1.0 else 0
            sy1 = min(nby - 1, int(math.floor(hi_y))) if hi_y < nby else nby - 1
        ca, cb, cc, smax = par[s + k, 2], par[s + k, 3], par[s + k, 4], par[s + k, 6]
        for by in range(sy0, sy1 + 1):
            for bx in range(sx0, sx1 + 1):
                # the box's blocks whose pixel centres the ellipse misses (its corners, or a pixel row it only grazes):
                # 45 % of a kitchen map's block entries at 1/4 scale (3.53M -> 1.95M). The kernels' own per-pixel
                # test, in the same float32, so a block left out is one where every pixel skips the Gaussian anyway
                hit = False
                for p in range(bw * bh):
                    hit = hit | reaches(np.float32(x0 + bx * bw + p % bw), np.float32(y0 + by * bh + p // bw), mx, my,
                                        ca, cb, cc, smax)
                # written whether or not it hits (the next entry overwrites a miss; a list has room for all n), so
                # that the outcome, a coin flip in the box's border blocks, is not a branch to mispredict
                j = by * nbx + bx
                sub[base + j * n + sub_n[t, j]] = k
                sub_n[t, j] += 1 if hit else 0


# The compositing kernels' parallel tasks: this many per thread, each taking every slots-th tile of the heaviest-first
# order and allocating its pixel-block scratch once (allocating it per tile inside the parallel loop held two threads
# to 1.5-1.6x over one on a 1/4-scale render; once per task, 1.9-2.0x, see renderers.md "Threads"). Several tasks per
# thread, taken dynamically, still let a core that falls behind (a busy machine) hand work to the others.
SLOTS_PER_THREAD = 4


def task_slots(items: int) -> int:
    """The parallel task count for ``items`` work items (the compositing kernels' tiles, the binning's Gaussians) on
    numba's current threads; an argument of the kernels, not read inside them: a kernel that calls
    ``numba.get_num_threads`` cannot be cached on disk."""
    return max(1, min(items, SLOTS_PER_THREAD * numba.get_num_threads()))


def run(kernel, *args) -> None:
    """Call a kernel with chunks of one tile, so that idle cores take the next tile (dynamic load balance)."""
    old = numba.set_parallel_chunksize(1)
    try:
        kernel(*args)
    finally:
        numba.set_parallel_chunksize(old)


# ------------------------------------------------------------------------------------ block shape per target ----

# Pixels per block -> (width, height). One shape serves every target measured (benchmarks/speed/cpu_targets.py): 16
# float32 lanes are one AVX-512 register and two AVX2 or four SSE/NEON registers, and LLVM vectorises the 16-pixel
# loop at each target's width. 8-pixel blocks (4x2) were measured 3-6x slower on every target: LLVM unrolls an
# 8-trip loop fully before its loop vectoriser sees it and the unrolled body stays scalar. The shape is a
# compile-time parameter of the kernels, so another one is one entry here (and the agreement tests cover it).
BLOCKS = {16: (4, 4)}


def target_features() -> tuple[str, str]:
    """(CPU name, feature string) numba compiles for: ``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``, else the host's."""
    import llvmlite.binding as ll
    from numba.core.codegen import get_host_cpu_features
    name = numba.config.CPU_NAME or ll.get_host_cpu_name()
    feats = numba.config.CPU_FEATURES
    if feats is None:
        feats = get_host_cpu_features()
    return name, feats


def isa_of(feats: str, machine: str) -> str:
    """The vector ISA an LLVM feature string (``"+avx2,-avx512f,..."``) enables on ``machine`` (``platform.machine()``).

    x86-64: its widest extension (``avx512f``, ``avx2``, ``avx``, ``sse4.2``, else ``baseline``). aarch64 / arm64:
    ``neon`` (Advanced SIMD, "asimd" in /proc/cpuinfo), which every ARMv8-A CPU has and LLVM's generic aarch64 target
    enables, so a string that does not mention it still has it (only ``-neon`` removes it); then ``+sve`` / ``+sve2``
    where the string enables them. An empty string (a named CPU's own features, which numba does not list) says so.
    """
    on = {f[1:] for f in feats.split(",") if f.startswith("+")}
    off = {f[1:] for f in feats.split(",") if f.startswith("-")}
    if machine.lower() in ("aarch64", "arm64"):
        isa = "+".join(["neon"] * ("neon" not in off) + [x for x in ("sve", "sve2") if x in on]) or "baseline"
        return isa if feats else f"{isa}, its own features"
    if not feats:
        return "its own features"
    return next((x for x in ("avx512f", "avx2", "avx", "sse4.2") if x in on), "baseline")


def target_summary() -> str:
    """e.g. ``znver5 (host; avx512f)``, ``haswell (avx2)``, ``neoverse-v1 (host; neon+sve)``, ``generic (host; neon)``
    (aarch64 under qemu-user, whose /proc/cpuinfo is the x86 host's): the CPU and ISA the kernels are built for."""
    import platform
    name, feats = target_features()
    host = numba.config.CPU_NAME is None
    return f"{name} ({'host; ' if host else ''}{isa_of(feats, platform.machine())})"


def default_block() -> int:
    """Pixels per block of the compositing kernels on the target numba compiles for (today 16 on every target)."""
    return 16
