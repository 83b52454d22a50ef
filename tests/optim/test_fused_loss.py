"""The fused supervision loss of a ``cpu`` render (optim.loss_kernels): the same value, error map and gradient as
the torch formulation of ``supervision_loss``, which every other renderer uses."""

import dataclasses

import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.optim.losses import LossConfig, supervision_loss
from eligsir_o3d.render import get_renderer
from eligsir_o3d.render.base import RenderOutput, finish


def _accumulations(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(h, w, generator=g)
    alpha[0, :5] = 0.0  # nothing drawn
    alpha[1, :3] = 5e-5  # below the depth normalisation's floor
    rgb = torch.rand(h, w, 3, generator=g) * alpha[..., None]
    dep = (1.0 + 2.0 * torch.rand(h, w, generator=g)) * alpha
    ref = torch.rand(h, w, 3, generator=g)
    ref_depth = 1.0 + 2.0 * torch.rand(h, w, generator=g)
    ref_depth[::3, ::4] = 0.0  # missing measurements
    return torch.cat([rgb, dep[..., None]], -1), alpha, ref, ref_depth


def _loss(acc, alpha, background, ref, ref_depth, cfg, fused):
    acc, alpha = acc.clone().requires_grad_(True), alpha.clone().requires_grad_(True)
    color, depth, a = finish(acc[..., :3], acc[..., 3], alpha, background)
    out = RenderOutput(color, depth, a, torch.zeros(0, dtype=torch.int32),
                       raw=(acc, alpha, background) if fused else None)
    loss, error = supervision_loss(out, ref, ref_depth, cfg)
    (2.0 * loss).backward()
    # the torch formulation leaves alpha's gradient None where the loss does not depend on it
    return loss, error, acc.grad, torch.zeros_like(alpha) if alpha.grad is None else alpha.grad


@pytest.mark.parametrize("hw", [(30, 41), (7, 9), (3, 4)])
@pytest.mark.parametrize("background", [None, (0.2, 0.5, 0.9)])
@pytest.mark.parametrize("change", [{}, {"lambda_dssim": 0.0}, {"lambda_depth": 0.0}, {"depth_alpha_min": 0.0}])
def test_fused_loss_equals_the_torch_formulation(hw, background, change):
    acc, alpha, ref, ref_depth = _accumulations(*hw, seed=len(change))
    bg = None if background is None else torch.tensor(background)
    cfg = dataclasses.replace(LossConfig(), **change)
    fused = _loss(acc, alpha, bg, ref, ref_depth, cfg, True)
    torch_ = _loss(acc, alpha, bg, ref, ref_depth, cfg, False)
    torch.testing.assert_close(fused[0], torch_[0], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(fused[1], torch_[1], rtol=1e-6, atol=1e-7)
    for g_f, g_t in zip(fused[2:], torch_[2:]):
        torch.testing.assert_close(g_f, g_t, rtol=1e-4, atol=1e-6 * float(g_t.abs().max()))


def test_cpu_render_takes_the_fused_path_with_the_same_gradients():
    """Through a cpu render: the loss differentiated into the compositing's accumulations gives the Gaussians the
    gradients of the torch formulation (which differentiates the finished colour and depth)."""
    g = torch.Generator().manual_seed(1)
    n = 300
    means = torch.randn(n, 3, generator=g) * 0.6 + torch.tensor([0.0, 0.0, 3.0])
    params = [means, torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
              torch.rand(n, 3, generator=g) * 0.1 + 0.02, torch.rand(n, generator=g) * 0.8 + 0.1,
              torch.rand(n, 3, generator=g)]
    cam = Camera(48, 36, 40.0, 40.0, 23.5, 17.5)
    ref = torch.rand(36, 48, 3, generator=g)
    ref_depth = torch.full((36, 48), 3.0)
    renderer = get_renderer("cpu", "cpu")
    grads = []
    for fused in (True, False):
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = renderer.render(*leaves, cam, torch.eye(4).numpy(), torch.tensor([0.1, 0.1, 0.1]))
        assert out.raw is not None
        if not fused:
            out.raw = None
        supervision_loss(out, ref, ref_depth, LossConfig())[0].backward()
        grads.append([leaf.grad for leaf in leaves])
    for g_f, g_t in zip(*grads):
        torch.testing.assert_close(g_f, g_t, rtol=1e-4, atol=1e-6 * float(g_t.abs().max()))
