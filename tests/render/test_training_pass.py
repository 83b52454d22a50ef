"""The ``cpu`` renderer's training pass (``CpuRenderer.render_training``, no autograd) against its render through
autograd: the same accumulations and the same gradients of every input, bit for bit, on one thread and on two; and
the numba kernel set's update takes it without changing a map's bits."""

from __future__ import annotations

import numba
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.render.cpu_backend import CpuRenderer

from tests.render.test_render_agreement import edge_case_scene

NAMES = ("means", "quats", "scales", "opacities", "colors")


def _weights(h: int, w: int):
    g = torch.Generator().manual_seed(3)
    return torch.randn(h, w, 4, generator=g), torch.randn(h, w, generator=g)


def _through_autograd(renderer, params, camera, T, background):
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = renderer.render(*(leaves[k] for k in NAMES), camera, T, background)
    acc, alpha, _ = out.raw
    g_acc, g_alpha = _weights(camera.height, camera.width)
    torch.autograd.backward((acc, alpha), (g_acc, g_alpha))
    return acc.detach(), alpha.detach(), out.radii, {k: leaves[k].grad for k in NAMES}


def _training_pass(renderer, params, camera, T, background):
    out = renderer.render_training(*(params[k] for k in NAMES), camera, T, background)
    acc, alpha, _ = out.raw
    g_acc, g_alpha = _weights(camera.height, camera.width)
    grads = out.training_pass.backward(g_acc, g_alpha)
    return acc, alpha, out.radii, dict(zip(NAMES, grads))


@pytest.mark.parametrize("threads", [1, 2])
def test_the_training_pass_gives_the_autograd_render_bit_for_bit(threads):
    params, T = edge_case_scene(n=600, seed=4)
    params = {k: v.contiguous() for k, v in params.items()}
    camera = Camera(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
    background = torch.tensor([0.2, 0.4, 0.6])
    renderer = CpuRenderer()
    old = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        ref = _through_autograd(renderer, params, camera, T, background)
        got = _training_pass(renderer, params, camera, T, background)
    finally:
        numba.set_num_threads(old)
    for a, b in zip(got[:3], ref[:3]):
        assert torch.equal(a, b)
    assert (ref[2] > 0).sum() > 100  # the scene draws most of its Gaussians
    for name in NAMES:
        assert got[3][name].is_contiguous()
        assert torch.equal(got[3][name], ref[3][name]), name


def test_the_training_pass_takes_only_float32_contiguous_rgb():
    params, T = edge_case_scene(n=50, seed=1)
    camera = Camera(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
    args = [params[k] for k in NAMES]
    with pytest.raises(ValueError, match="float32"):
        CpuRenderer().render_training(*args[:4], args[4].double(), camera, T)
    with pytest.raises(ValueError, match="colors"):
        CpuRenderer().render_training(*args[:4], torch.zeros(50, 4, 3), camera, T)
