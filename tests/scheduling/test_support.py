"""The support probe's masks (eligsir_o3d/scheduling/support.py): made where the render is, and packed into one byte
per pixel for the copy to the host without changing them."""

import pytest
import torch

from eligsir_o3d.scheduling.support import SupportConfig, support_masks

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_packed_masks_are_the_masks(device):
    g = torch.Generator().manual_seed(0)
    alpha = torch.rand(30, 40, generator=g)
    depth = torch.where(torch.rand(30, 40, generator=g) < 0.2, 0.0, 0.5 + 3 * torch.rand(30, 40, generator=g))
    rdepth = depth + 0.2 * torch.randn(30, 40, generator=g)
    cfg = SupportConfig()
    want = support_masks(alpha, rdepth, depth, cfg)
    got = support_masks(alpha.to(device), rdepth.to(device), depth.to(device), cfg, pack=True)
    for w, m in zip(want, got):
        assert m.dtype == torch.bool and m.device.type == "cpu" and torch.equal(m, w)
    unsupported, misplaced = want
    assert unsupported.any() and misplaced.any() and not (unsupported & misplaced).any()
    assert not (unsupported | misplaced)[depth == 0].any()  # no depth: neither
    assert torch.equal(unsupported, (depth > 0) & (alpha < cfg.alpha_min))
