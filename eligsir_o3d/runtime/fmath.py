"""Float32 scalar functions with fixed bits for the compiled CPU kernels: ``exp_neg`` (exp(-s) for s >= 0, the
compositing kernels'), ``exp32`` (exp of any float32) and ``sigmoid32``, and the powers of two they build from
exponent bits (``exp2``, ``exp2_neg``; the view test's scale bound uses the latter too).

``math.exp`` in a numba kernel is whatever LLVM makes of it: with numba's SVML (the ``icc_rt`` package) a vector
library call where a loop vectorises and scalar libm where it does not (a ``prange`` loop's remainder, a serial
loop), which round differently; elsewhere another machine's libm. These are branch-free polynomials in float32 and
int32 steps only, so a loop of them vectorises to the width of its float32 vector and every lane, vectorised or
scalar, parallel or serial, on any number of threads, with or without SVML, gives the same bits. The exps are
within 2 ulp of exp over their ranges, the sigmoid within 3 (its three roundings, as torch's float32 sigmoid).

Method: x = n ln2 + r with n the nearest integer (Cody-Waite: ``LN2_HI`` has 16 significant bits, so n ``LN2_HI`` is
exact for |n| <= 127), exp(r) on r in [-ln2/2, ln2/2] by its degree-7 Taylor polynomial (truncation < 1e-8
relative), and 2^n built from its exponent bits. ``exp32`` clamps its argument to [-87, 88] (the normal float32
range: exp(88) = 1.7e38), so it never returns 0 or inf; ``exp_neg`` clamps s to [0, 16] (the compositing kernels do
not use the value beyond). NaN in, NaN out for ``exp32`` and ``sigmoid32``.

Every kernel compiled through :mod:`.jit` carries this file's checksum in its disk-cache key
(:data:`.jit.HELPERS_CRC`), so an edit here recompiles the kernels that inline these.
"""

from __future__ import annotations

import math

from . import jit as _setup  # noqa: F401  (the process-level set-up before numba)

import numba  # noqa: E402
import numpy as np  # noqa: E402
from llvmlite import ir  # noqa: E402
from numba import types  # noqa: E402
from numba.extending import intrinsic  # noqa: E402

HALF = np.float32(0.5)
ONE = np.float32(1.0)
ZERO = np.float32(0.0)
SIG_CLAMP = np.float32(16.0)
EXP_LO = np.float32(-87.0)
EXP_HI = np.float32(88.0)
ROUND_SHIFT = np.float32(128.5)  # x log2e + 128.5 > 0 over [EXP_LO, EXP_HI]: truncation rounds to nearest
SHIFT = np.float32(128.0)
LOG2E = np.float32(1.4426950408889634)
LN2_HI = np.float32(0.693145751953125)
LN2_LO = np.float32(1.4286068203094173e-06)
E0, E1, E2, E3, E4, E5, E6, E7 = (np.float32((-1.0) ** i / math.factorial(i)) for i in range(8))
P0, P1, P2, P3, P4, P5, P6, P7 = (np.float32(1.0 / math.factorial(i)) for i in range(8))


@intrinsic
def exp2_neg(typingctx, n):
    """2^-n for an integer-valued float32 n in [0, 126]: the float32 whose exponent field is 127 - n."""
    sig = types.float32(types.float32)

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        k = builder.fptosi(args[0], i32)
        bits = builder.shl(builder.sub(ir.Constant(i32, 127), k), ir.Constant(i32, 23))
        return builder.bitcast(bits, ir.FloatType())
    return sig, codegen


@intrinsic
def exp2(typingctx, n):
    """2^n for an integer-valued float32 n in [-126, 127]: the float32 whose exponent field is n + 127."""
    sig = types.float32(types.float32)

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        k = builder.fptosi(args[0], i32)
        bits = builder.shl(builder.add(k, ir.Constant(i32, 127)), ir.Constant(i32, 23))
        return builder.bitcast(bits, ir.FloatType())
    return sig, codegen


@numba.njit(inline="always", fastmath=False)
def exp_neg(s):
    """exp(-s) in float32 for s in [0, 16] (clamped there)."""
    s = min(max(s, ZERO), SIG_CLAMP)
    fn = np.float32(np.int32(s * LOG2E + HALF))  # round to nearest: s >= 0
    r = (s - fn * LN2_HI) - fn * LN2_LO
    p = ((((((E7 * r + E6) * r + E5) * r + E4) * r + E3) * r + E2) * r + E1) * r + E0
    return p * exp2_neg(fn)


@numba.njit(inline="always", fastmath=False)
def exp32(x):
    """exp(x) in float32, x clamped to [-87, 88]; NaN stays NaN."""
    x = np.float32(x)
    xc = min(max(x, EXP_LO), EXP_HI)
    fn = np.float32(np.int32(xc * LOG2E + ROUND_SHIFT)) - SHIFT
    r = (xc - fn * LN2_HI) - fn * LN2_LO
    p = ((((((P7 * r + P6) * r + P5) * r + P4) * r + P3) * r + P2) * r + P1) * r + P0
    y = p * exp2(fn)
    return y if x == x else x


@numba.njit(inline="always", fastmath=False)
def sigmoid32(x):
    """1 / (1 + exp(-x)) in float32 through :func:`exp32`."""
    return ONE / (ONE + exp32(-np.float32(x)))
