"""runtime.jit.full_width_vectors: the function attribute that lets LLVM use the target's full vector width lands
on the function a kernel's loop body compiles to, and changes no result."""

import re

import numba
import numpy as np
from numba import prange

from eligsir_o3d.runtime.jit import full_width_vectors


def _kernel(x, out):
    for i in prange(x.shape[0]):
        full_width_vectors()
        acc = np.float32(0.0)
        for j in range(16):
            acc += x[i, j] * np.float32(j)
        out[i] = acc


def test_the_attribute_is_on_the_parallel_body_and_the_values_are_unchanged():
    kern = numba.njit(parallel=True, cache=False)(_kernel)
    x = np.random.default_rng(0).random((64, 16), dtype=np.float32)
    out = np.empty(64, np.float32)
    kern(x, out)
    ref = np.empty(64, np.float32)
    numba.njit(parallel=False, cache=False)(_kernel)(x, ref)  # the serial twin: the same bits
    assert np.array_equal(out, ref)
    ir = "".join(kern.inspect_llvm().values())
    # the attribute is printed on the function or in an attribute group that a function of the module uses
    assert re.search(r'"prefer-vector-width"="512"', ir)
