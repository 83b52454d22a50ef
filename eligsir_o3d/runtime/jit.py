"""The numba decorators every compiled CPU kernel uses (the renderer's, the optimiser's update and D-SSIM kernels).

``jit`` compiles a parallel kernel (``prange``), ``jit_serial`` a serial one; both are ``njit(cache=True)`` without
fast-math (every target computes the same bits). numba's disk cache checks only the source file of the cached
function itself, so every kernel's cache key also carries the checksum of :mod:`.fmath` (the scalar helpers that
kernels inline): an edit there recompiles them. Where numba finds no writable cache location the kernel still
works, compiled once per process, after one warning. Importing this module runs the process-level set-up
(:func:`eligsir_o3d.runtime.prepare`), imports numba and picks the threading layer, so only kernel modules import
it (``import eligsir_o3d`` stays free of numba)."""

from __future__ import annotations

import os
import time
import warnings
import zlib
from contextlib import contextmanager

from . import prepare, tbb

prepare()  # the tbb wheel's library before Open3D's: numba's TBB layer needs the newer one

import numba  # noqa: E402

from numba import types  # noqa: E402
from numba.core.caching import FunctionCache  # noqa: E402
from numba.extending import intrinsic  # noqa: E402

uncached: list[str] = []  # names of the kernels that compile in every process (no writable cache)

with open(os.path.join(os.path.dirname(__file__), "fmath.py"), "rb") as _f:
    HELPERS_CRC = zlib.crc32(_f.read())


class _HelpersKeyedCache(FunctionCache):
    """numba's per-function disk cache with :data:`HELPERS_CRC` in every entry's key."""

    def _index_key(self, sig, codegen):
        return (*super()._index_key(sig, codegen), HELPERS_CRC)


def _select_threading_layer() -> bool:
    """TBB where a recent enough one is loaded (:mod:`.tbb`: its workers need no wake-up per parallel region),
    else OpenMP, never an old system TBB (numba would warn and skip it); the user's choice wins. True when the
    kernels will run on TBB."""
    if "NUMBA_THREADING_LAYER" in os.environ or "NUMBA_THREADING_LAYER_PRIORITY" in os.environ:
        return os.environ.get("NUMBA_THREADING_LAYER", "").lower() == "tbb"
    on_tbb = tbb.usable()
    numba.config.THREADING_LAYER_PRIORITY = (["tbb", "omp"] if on_tbb else ["omp", "tbb"]) + ["workqueue"]
    return on_tbb


ON_TBB = _select_threading_layer()


def compile_kernel(parallel: bool, fastmath: bool = False):
    """``njit(cache=True)`` decorator; without a writable cache location, fall back to an uncached kernel."""
    def deco(fn):
        opts = dict(parallel=parallel, fastmath=fastmath, nogil=True)
        try:
            kernel = numba.njit(cache=True, **opts)(fn)
            kernel._cache = _HelpersKeyedCache(kernel.py_func)
            return kernel
        except RuntimeError as err:  # numba: "cannot cache function ...: no locator available for file ..."
            if not uncached:
                warnings.warn(f"numba cannot cache the cpu renderer's kernels ({err}); they compile in every new "
                              "process. Set NUMBA_CACHE_DIR to a writable folder to keep them.", RuntimeWarning,
                              stacklevel=2)
            uncached.append(fn.__name__)
            return numba.njit(cache=False, **opts)(fn)
    return deco


jit = compile_kernel(parallel=True)
jit_serial = compile_kernel(parallel=False)


@intrinsic
def full_width_vectors(typingctx):
    """Called in a kernel's loop body: LLVM may vectorise the function it lands in (a ``prange`` body is a function
    of its own) at the target's full register width. x86 CPUs with AVX-512 default to 256-bit vectors (LLVM's
    ``prefer-256-bit`` tuning), which splits a 16-pixel block into two halves and the kernels' explicit 16-lane
    vector steps across them; the ``prefer-vector-width`` function attribute lifts that for this function alone
    (the process's other code keeps numba's target). No effect on a CPU without 512-bit registers; the same bits
    at any width (the kernels use no fast-math)."""
    def codegen(context, builder, signature, args):
        # llvmlite's FunctionAttributes takes enum attributes only; a string attribute is printed as given
        set.add(builder.function.attributes, '"prefer-vector-width"="512"')
        return context.get_dummy_value()
    return types.void(), codegen

from .row_threads import RowThreads  # noqa: E402
from .threads import PARALLEL_FLOOR_ROWS, PARALLEL_MIN_PIXELS, PARALLEL_MIN_ROWS  # noqa: E402
from .threads import PARALLEL_MIN_ROWS_TBB  # noqa: E402

ROWS_LIMIT = PARALLEL_MIN_ROWS_TBB if ON_TBB else PARALLEL_MIN_ROWS  # rows from which a per-Gaussian kernel runs parallel


@contextmanager
def threads_for(work: int, min_work: int):
    """Run the block's kernel calls on one numba thread when ``work`` < ``min_work``, else on numba's threads as
    set; the same bits either way (the kernels' parallel loops write disjoint outputs)."""
    if work >= min_work or numba.config.NUMBA_NUM_THREADS == 1:  # a pool of one thread: nothing to narrow
        yield
        return
    n = numba.get_num_threads()
    if n == 1:
        yield
        return
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(n)


ROW_THREADS = RowThreads()  # the process's choice for per-Gaussian kernels between the two limits


@contextmanager
def rows_threads(rows: int, key: str = "rows"):
    """Run the block's per-Gaussian kernel (projection, culling, Adam, ...) over ``rows`` Gaussians on numba's
    threads as set from :data:`ROWS_LIMIT` rows, on one below :data:`.threads.PARALLEL_FLOOR_ROWS`, and in between
    as :data:`ROW_THREADS` chooses for ``key`` (a name per kernel); yields whether it runs on more than one
    thread. The same bits either way."""
    n = numba.get_num_threads() if numba.config.NUMBA_NUM_THREADS > 1 else 1
    if n == 1 or rows >= ROWS_LIMIT:
        yield n > 1
        return
    measured = rows >= PARALLEL_FLOOR_ROWS
    parallel = measured and ROW_THREADS.choose(key, rows)
    if not parallel:
        numba.set_num_threads(1)
    t0 = time.perf_counter()
    try:
        yield parallel
    finally:
        if measured:
            ROW_THREADS.record(key, rows, parallel, time.perf_counter() - t0)
        if not parallel:
            numba.set_num_threads(n)


def pixels_threads(pixels: int):
    """:func:`threads_for` an image kernel (D-SSIM) over ``pixels`` pixels."""
    return threads_for(pixels, PARALLEL_MIN_PIXELS)
