"""The cpu renderer's record table: the backward kernel gives the same bits whether it reads the forward's records
of a tile or evaluates the tile again (a table too small for every tile records only those that fit)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render import cpu_backend as cb
from tests.render.test_render_agreement import edge_case_scene


def _inputs(camera, seed):
    params, T = edge_case_scene(seed=seed)
    with torch.no_grad():
        proj = cb.project_cpu(params["means"], params["quats"], params["scales"], camera, T)
        offsets, flat, tiles_x = cb.bin_tiles_csr(proj, camera.width, camera.height)
    f32 = np.float32
    k = cb._kernels()
    m, c = proj.means2d.numpy().astype(f32), proj.conics.numpy().astype(f32)
    o = params["opacities"].numpy().astype(f32)
    feats = np.concatenate([params["colors"].numpy(), proj.depths.numpy()[:, None]], 1).astype(f32)
    bounds = np.empty((m.shape[0], 3), f32)
    k.cull_bounds(c, o, bounds)
    order = np.argsort(-(offsets[1:] - offsets[:-1]).numpy(), kind="stable")
    return m, c, o, feats, bounds, offsets.numpy(), flat.numpy(), order, tiles_x


def _render(inputs, camera, records):
    """Forward and backward kernels with a record table of ``records`` records: outputs, gradients, the table."""
    k = cb._kernels()
    m, c, o, feats, bounds, off, fl, order, tiles_x = inputs
    H, W, f32 = camera.height, camera.width, np.float32
    outs = (np.empty((H, W, 4), f32), np.empty((H, W), f32), np.empty((H, W), f32), np.empty((H, W), np.int32))
    gathered = k.gather_buffers(fl.shape[0], off.shape[0] - 1, 16, records)
    slots = k.task_slots(order.shape[0])
    forward, backward = cb._compositors(16)
    need = k.run(forward, m, c, o, feats, bounds, off, fl, order, slots, tiles_x, W, H, *outs, *gathered)
    g = np.random.default_rng(0)
    gf, ga = g.standard_normal((H, W, 4)).astype(f32), g.standard_normal((H, W)).astype(f32)
    v_isect, v = np.empty((fl.shape[0], k.ISECT_COLS), f32), np.empty((m.shape[0], 10), f32)
    k.run(backward, *gathered, off, fl, order, slots, tiles_x, W, H, outs[2], outs[3], gf, ga, v_isect, v)
    return outs + (v, v_isect[:, :10]), gathered, need


@pytest.mark.parametrize("seed", [0, 1])
def test_records_and_recomputation_give_the_same_bits(seed):
    camera = Camera(70, 45, 55.0, 58.0, 30.0, 25.0)
    inputs = _inputs(camera, seed)
    full, tables, need = _render(inputs, camera, None)
    rec_i = tables[5]
    nb = tables[2].shape[1]
    assert need >= tables[2].sum()  # room for every block list entry
    assert (rec_i[:, :nb] >= 0).all() and rec_i[:, nb:].sum() > 0  # every tile recorded
    none, tables0, _ = _render(inputs, camera, 0)
    assert (tables0[5][:, :nb] == -1).all()  # no tile recorded: all evaluated again
    part, tables_p, _ = _render(inputs, camera, need // 2)
    recorded = (tables_p[5][:, 0] >= 0).sum()
    assert 0 < recorded < tables_p[5].shape[0]
    for a, b, p in zip(full, none, part):
        assert np.array_equal(a, b) and np.array_equal(a, p)


def test_record_table_is_bounded():
    k = cb._kernels()
    shapes = k.gather_shapes(10 ** 7, 1200, 16)
    assert shapes[4][0] * k.RECORD_BYTES <= k.RECORD_MAX_BYTES + k.RECORD_SPARE * k.RECORD_BYTES
    assert shapes[3][0] == 16 * shapes[4][0]
