import torch
from pytorch_msssim import ssim

from eligsir_o3d.optim import dssim


def test_dssim_matches_pytorch_msssim():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 52, 3, generator=g)
    b = (a + 0.1 * torch.randn(40, 52, 3, generator=g)).clamp(0, 1)
    ref = 1 - ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], data_range=1.0, win_size=11)
    torch.testing.assert_close(dssim(a, b), ref, rtol=1e-5, atol=1e-6)
    assert dssim(a, a).abs() < 1e-6
