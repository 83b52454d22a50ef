"""The compiled kernels' float32 scalar functions (eligsir_o3d.runtime.fmath): within 2 ulp of exp over their
ranges (the sigmoid within 3), and the same bits in a vectorised loop as one by one."""

import numba
import numpy as np

from eligsir_o3d.runtime.fmath import exp32, exp_neg, sigmoid32


@numba.njit
def _each(fn_id, x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        if fn_id == 0:
            out[i] = exp_neg(x[i])
        elif fn_id == 1:
            out[i] = exp32(x[i])
        else:
            out[i] = sigmoid32(x[i])
    return out


@numba.njit
def _exp32_loop(x, out):
    for i in range(x.shape[0]):  # vectorised by LLVM: no branch in the body
        out[i] = exp32(x[i])


@numba.njit
def _sigmoid32_loop(x, out):
    for i in range(x.shape[0]):
        out[i] = sigmoid32(x[i])


@numba.njit
def _exp_neg_loop(x, out):
    for i in range(x.shape[0]):
        out[i] = exp_neg(x[i])


def _ulps(got, ref):
    return np.abs(got.astype(np.float64) - ref) / np.spacing(ref.astype(np.float32)).astype(np.float64)


def test_exp_neg_is_within_two_ulp_of_exp():
    """exp(-s) against float64 exp, on [0, 16] where the compositing kernels use its values."""
    s = np.concatenate([np.linspace(0.0, 16.0, 200_001), np.random.default_rng(0).uniform(0, 6, 100_000)])
    s = s.astype(np.float32)
    assert float(_ulps(_each(0, s), np.exp(-s.astype(np.float64))).max()) < 2.0


def test_exp32_is_within_two_ulp_of_exp_and_clamps():
    x = np.concatenate([np.linspace(-87.0, 88.0, 400_001), np.random.default_rng(1).uniform(-12, 4, 200_000)])
    x = x.astype(np.float32)
    assert float(_ulps(_each(1, x), np.exp(x.astype(np.float64))).max()) < 2.0
    edge = _each(1, np.array([-1e4, -87.0, 88.0, 1e4, np.nan, 0.0], np.float32))
    assert edge[0] == edge[1] > 0 and edge[2] == edge[3] < np.inf and np.isnan(edge[4]) and edge[5] == 1.0


def test_sigmoid32_is_within_three_ulp_of_the_sigmoid():
    """1 / (1 + exp(-x)) rounds three times: torch's float32 sigmoid is 2.2 ulp off at x = -16.7 too."""
    x = np.concatenate([np.linspace(-30.0, 30.0, 300_001), np.random.default_rng(2).normal(0, 4, 200_000)])
    x = x.astype(np.float32)
    ref = 1.0 / (1.0 + np.exp(-x.astype(np.float64)))
    assert float(_ulps(_each(2, x), ref).max()) < 3.0
    assert np.isnan(_each(2, np.array([np.nan], np.float32))[0])


def test_a_vectorised_loop_gives_the_scalar_bits():
    """Lengths that leave a remainder after the vector body: every element, body or remainder, has the bits of the
    function called one at a time (the exps' loops vectorise; the sigmoid's division keeps numba's zero check, a
    branch, so its loop stays scalar)."""
    rng = np.random.default_rng(3)
    for n in (1, 7, 33, 1001):
        x = rng.uniform(-20, 20, n).astype(np.float32)
        s = np.abs(x) * np.float32(0.8)
        for loop, fn_id, arg in ((_exp32_loop, 1, x), (_sigmoid32_loop, 2, x), (_exp_neg_loop, 0, s)):
            out = np.empty_like(arg)
            loop(arg, out)
            assert np.array_equal(out.view(np.int32), _each(fn_id, arg).view(np.int32))
