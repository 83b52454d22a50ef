import pytest
import torch
from pytorch_msssim import ssim

from eligsir_o3d.optim.losses import dssim, dssim_torch


def _pair(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, 3, generator=g)
    b = (a + 0.1 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    return a, b


@pytest.mark.parametrize("fn", [dssim, dssim_torch])
def test_dssim_matches_pytorch_msssim(fn):
    a, b = _pair(40, 52)
    ref = 1 - ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0, win_size=11)
    torch.testing.assert_close(fn(a, b), ref, rtol=1e-5, atol=1e-6)
    assert fn(a, a).abs() < 1e-6


@pytest.mark.parametrize("hw", [(40, 52), (60, 80), (13, 17), (7, 9)])
def test_cpu_dssim_kernel_value_and_gradient_match_the_torch_formulation(hw):
    # the kernel computes value and gradient in float32 in one pass; the reference is torch autograd in float64
    a, b = _pair(*hw, seed=1)
    pred = a.clone().requires_grad_(True)
    value = dssim(pred, b)
    (3.0 * value).backward()  # the upstream gradient scales the stored one
    pred64 = a.double().requires_grad_(True)
    ref = dssim_torch(pred64, b.double())
    (3.0 * ref).backward()
    torch.testing.assert_close(value.double(), ref.detach(), rtol=1e-5, atol=1e-6)
    scale = pred64.grad.abs().max()
    torch.testing.assert_close(pred.grad.double(), pred64.grad, rtol=1e-3, atol=1e-4 * float(scale))
