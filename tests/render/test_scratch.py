"""The reused scratch tables of the cpu renderer: a table is never shared by two renders in flight, and reuse
changes no result."""

from __future__ import annotations

import numpy as np
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render.cpu_backend import CpuRenderer
from eligsir_o3d.render.scratch import ScratchPool

from test_render_agreement import PARAMS, edge_case_scene, look_at_pose


def _address(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


def test_pool_hands_out_a_set_only_when_no_view_of_it_is_held():
    pool = ScratchPool((np.float32, np.int32), keep=2)
    a = pool.take((100, 11), (1600,))
    b = pool.take((100, 11), (1600,))
    assert a[0].shape == (100, 11) and a[1].shape == (1600,) and a[0].dtype == np.float32 and a[1].dtype == np.int32
    assert not np.shares_memory(a[0], b[0]) and not np.shares_memory(a[1], b[1])
    c = pool.take((10, 11), (160,))  # both kept sets are held: a fresh one, not kept
    assert not np.shares_memory(c[0], a[0]) and not np.shares_memory(c[0], b[0]) and len(pool.sets) == 2
    first = _address(a[0])
    par_only = a[0]
    del a
    d = pool.take((90, 11), (1440,))  # the first set's int table is free, its float table is not: not handed out
    assert not np.shares_memory(d[0], par_only)
    del par_only, d
    e = pool.take((90, 11), (1440,))  # now free: reused, smaller views of the same memory
    assert _address(e[0]) == first and e[0].shape == (90, 11)
    del e
    f = pool.take((300, 11), (4800,))  # free but too small: replaced by a larger set (a quarter more)
    assert f[0].shape == (300, 11) and pool.sets[0][0].size == 300 * 11 * 5 // 4
    assert len(pool.sets) == 2


def test_pool_does_not_keep_sets_above_its_size_limit():
    pool = ScratchPool((np.float32,), keep=2, max_bytes=1000)
    a = pool.take((500,))
    assert a[0].shape == (500,) and pool.sets == []


def _grads(out, ps, seed):
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(out.color.shape, generator=g)
    return torch.autograd.grad((out.color * w).sum() + out.depth.sum(), [ps[k] for k in PARAMS])


def test_two_renders_in_flight_keep_their_own_tables():
    """Render two views, then back-propagate them in the other order: the same gradients as one at a time."""
    params, T = edge_case_scene(seed=3)
    T2 = look_at_pose([0.4, -0.2, -2.8])
    cam = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
    r = CpuRenderer()

    def render(pose):
        ps = {k: v.clone().requires_grad_(True) for k, v in params.items()}
        return ps, r.render(ps["means"], ps["quats"], ps["scales"], ps["opacities"], ps["colors"], cam, pose)

    alone = []
    for pose, seed in ((T, 1), (T2, 2)):
        ps, out = render(pose)
        alone.append(_grads(out, ps, seed))
    (ps1, out1), (ps2, out2) = render(T), render(T2)
    for _ in range(3):  # more renders in between, which must not take the tables held by the two above
        with torch.no_grad():
            render(T2)
    later = _grads(out2, ps2, 2), _grads(out1, ps1, 1)
    for a, b in zip(alone, later[::-1]):
        for x, y in zip(a, b):
            assert torch.equal(x, y)
