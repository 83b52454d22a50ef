"""Policies and the loss read only colour, depth and alpha of a RenderOutput: ``radii``, ``visible`` and ``means2d``
mean different things per backend (see RenderOutput's docstring), so a decision built on them would change with the
renderer. Checked two ways: statically over the modules, and by mapping with outputs whose per-Gaussian fields raise."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import eligsir_o3d
from eligsir_o3d.render.base import RenderOutput

BACKEND_SPECIFIC = ("radii", "visible", "means2d")
PACKAGE = Path(eligsir_o3d.__file__).parent


def test_no_policy_or_loss_module_names_the_backend_specific_fields():
    modules = sorted((PACKAGE / "scheduling").glob("*.py")) + [PACKAGE / "optim" / "losses.py", PACKAGE / "mapper" / "reconstructor.py"]
    hits = []
    for path in modules:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Attribute) and node.attr in BACKEND_SPECIFIC:
                hits.append(f"{path.name}:{node.lineno} .{node.attr}")
    assert not hits, hits


class _Guarded(RenderOutput):
    def __getattribute__(self, name):
        if name in BACKEND_SPECIFIC:
            raise AssertionError(f"RenderOutput.{name} was read during mapping")
        return super().__getattribute__(name)


class _GuardedRenderer:
    def __init__(self, inner):
        self.inner, self.name = inner, inner.name

    def render(self, *args, **kw):
        out = self.inner.render(*args, **kw)
        return _Guarded(out.color, out.depth, out.alpha, out.radii, out.means2d)


@pytest.mark.parametrize("ablate", [(), ("views", "fidelity", "growth")])
def test_mapping_never_reads_the_backend_specific_fields(ablate):
    import open3d as o3d

    import eligsir_o3d as eo3d

    guarded = _Guarded(*(np.zeros(1),) * 5)
    for name in BACKEND_SPECIFIC:  # the guard itself works
        with pytest.raises(AssertionError, match=name):
            getattr(guarded, name)
    w, h = 48, 36
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    color = (((u // 6 + v // 6) % 2)[..., None] * np.array([180, 40, 60]) + 50).astype(np.uint8)
    rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(color), o3d.t.geometry.Image(np.full((h, w), 1500, np.uint16)))
    cfg = eo3d.Config(renderer="cpu", ablate=ablate)
    cfg.clock.mode, cfg.clock.updates_per_frame = "updates", 4
    cfg.growth.seed_stride = 1
    cfg.growth.mcmc.refine_start = cfg.growth.mcmc.refine_every = 4
    rec = eo3d.Reconstructor(o3d.camera.PinholeCameraIntrinsic(w, h, 40.0, 40.0, 23.5, 17.5), "cpu", cfg)
    rec.renderer = _GuardedRenderer(rec.renderer)
    for i in range(4):
        T = np.eye(4)
        T[0, 3] = 0.05 * i
        rec.integrate(rgbd, T, timestamp=i / 30.0)
    rec.finalize()
    assert rec.stats.updates > 0 and len(rec.gmap) > 0


def test_cpu_render_composites_colour_and_depth_when_read_as_an_eager_render_does():
    """The cpu renderer's output defers the background composite and depth normalisation (base.finish) to the first
    read of color or depth: the same tensors as finish() of its accumulations, gradients included."""
    import torch

    from eligsir_o3d.core.camera import Camera
    from eligsir_o3d.render import get_renderer
    from eligsir_o3d.render.base import DeferredRenderOutput, finish

    g = torch.Generator().manual_seed(0)
    n = 40
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([1.0, 0.8, 0.5]) + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    scales = torch.full((n, 3), 0.05)
    opac = torch.full((n,), 0.6)
    colors = torch.rand(n, 3, generator=g).requires_grad_(True)
    cam, bg = Camera(32, 24, 30.0, 30.0, 15.5, 11.5), torch.tensor([0.2, 0.3, 0.4])
    out = get_renderer("cpu").render(means, quats, scales, opac, colors, cam, np.eye(4), bg)
    assert isinstance(out, DeferredRenderOutput) and "color" not in vars(out)  # not composited yet
    acc, alpha, background = out.raw
    color, depth, _ = finish(acc[..., :3], acc[..., 3], alpha, background)
    assert torch.equal(out.color, color) and torch.equal(out.depth, depth) and out.alpha is alpha
    assert out.color is out.color  # composited once
    out.color.sum().backward(retain_graph=True)
    expected = torch.autograd.grad(color.sum(), colors)[0]
    assert torch.equal(colors.grad, expected)
    with pytest.raises(AttributeError, match="nope"):
        out.nope
