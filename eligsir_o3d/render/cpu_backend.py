"""``cpu`` renderer: the reference's math (projection, tile binning, compositing) in compiled numba kernels.

Three steps, each the reference's twin and each tested against it, each a pass of :mod:`.cpu_passes`:
- projection (:mod:`._cpu_projection`): EWA covariance, Jacobian clamp, conic, radius and culling, per Gaussian, with
  a hand-written backward pass, as a ``torch.autograd.Function`` (the torch version costs ~40% of a 160x120 render);
- tile binning (:func:`.cpu_passes.bin_tiles_csr`): the reference's per-tile, front-to-back lists, compressed
  instead of padded;
- compositing (:mod:`._cpu_forward`, :mod:`._cpu_backward`, shared parts in :mod:`._cpu_kernels`): forward and
  backward kernels, as a ``torch.autograd.Function``; the forward's gathered tiles, which the backward reads, live
  in tables reused from render to render (:mod:`.scratch`).
A training update of RGB Gaussians takes the same passes without autograd (:meth:`CpuRenderer.render_training`).
The kernels run in parallel on the threads numba may use (``NUMBA_NUM_THREADS`` / ``numba.set_num_threads``).
Float32 throughout; inputs of other dtypes are cast and the gradients cast back. Background and depth
normalisation stay in torch (:func:`.base.finish`), shared with every backend, and run when a render's colour or
depth is first read (:class:`.base.DeferredRenderOutput`: a training update's fused loss reads the accumulations).
"""

from __future__ import annotations

import torch

from ..core.camera import Camera
from .base import DeferredRenderOutput, RenderOutput, TileRenderer, mask_culled, view_colors
from .cpu_passes import (TrainingPass, as_dtype, bin_tiles_csr, composite_backward, composite_forward, float32,
                         project_backward, project_forward, tile_order, view_arrays, warmup)
from .projection import EPS2D, Projection, TileBins

__all__ = ["CpuRenderer", "TrainingPass", "bin_tiles_csr", "project_cpu", "tile_lists", "warmup"]


class _Composite(torch.autograd.Function):
    """(means2d [N,2], conics [N,3], opacities [N], feats [N,4] rgb+depth) -> (accumulated feats [H,W,4], alpha [H,W])."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, offsets, flat_ids, order, tiles_x, width, height, block):
        m, c, o, f = (float32(x).numpy() for x in (means2d, conics, opacities, feats))
        out_feats, out_alpha, ctx.tiles = composite_forward(m, c, o, f, offsets, flat_ids, order, tiles_x, width,
                                                             height, block)
        ctx.dtypes = [means2d.dtype, conics.dtype, opacities.dtype, feats.dtype]
        return as_dtype(out_feats, feats.dtype), as_dtype(out_alpha, feats.dtype)

    @staticmethod
    def backward(ctx, grad_feats, grad_alpha):
        t = ctx.tiles
        if grad_feats is None:
            grad_feats = torch.zeros(t.height, t.width, t.n_feat)
        if grad_alpha is None:
            grad_alpha = torch.zeros(t.height, t.width)
        v = composite_backward(t, float32(grad_feats).numpy(), float32(grad_alpha).numpy())
        grads = (v[:, 0:2], v[:, 2:5], v[:, 5], v[:, 6:])
        grads = tuple(as_dtype(g, dt) for g, dt in zip(grads, ctx.dtypes))
        return grads + (None,) * 7


class _Project(torch.autograd.Function):
    """(means [N,3], quats [N,4], scales [N,3]) -> (means2d [N,2], conics [N,3], depths [N], radii [N] int32)."""

    @staticmethod
    def forward(ctx, means, quats, scales, V, cam):
        m, q, s = float32(means), float32(quats), float32(scales)
        means2d, conics, depths, radii = project_forward(m.numpy(), q.numpy(), s.numpy(), V, cam)
        ctx.save_for_backward(m, q, s)
        ctx.V, ctx.cam, ctx.dtypes = V, cam, (means.dtype, quats.dtype, scales.dtype)
        ctx.mark_non_differentiable(radii)
        dt = means.dtype
        return as_dtype(means2d, dt), as_dtype(conics, dt), as_dtype(depths, dt), radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        m, q, s = ctx.saved_tensors
        n = m.shape[0]
        grads = [g if g is not None else torch.zeros(shape) for g, shape in
                 ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_depths, (n,)))]
        vs = project_backward(m.numpy(), q.numpy(), s.numpy(), ctx.V, ctx.cam, *(float32(g).numpy() for g in grads))
        return tuple(as_dtype(v, dt) for v, dt in zip(vs, ctx.dtypes)) + (None, None)


def project_cpu(means, quats, scales, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> Projection:
    """:func:`.projection.project` in compiled code (forward and backward); same values up to float32 rounding."""
    V, cam = view_arrays(camera, T_world_cam, low_pass)
    means2d, conics, depths, radii = _Project.apply(means, quats, scales, V, cam)
    return Projection(means2d, conics, depths, radii)


def tile_lists(bins: TileBins) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded per-tile ids [T, K] -> (offsets [T + 1], flat ids [M]), int64."""
    ids = bins.ids.cpu()
    valid = ids >= 0
    offsets = torch.zeros(ids.shape[0] + 1, dtype=torch.long)
    torch.cumsum(valid.sum(1), 0, out=offsets[1:])
    return offsets, ids[valid].contiguous()


def _check_shapes(means, quats, scales, opacities, colors) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    want = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
            "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    for name, (t, shape) in want.items():
        if tuple(t.shape) != shape or t.device.type != "cpu":
            raise ValueError(f"cpu renderer: {name} must be a CPU tensor of shape {list(shape)} with N = "
                             f"{n} (from means), got {list(t.shape)} on {t.device}")


def _output(acc, alpha, radii, means2d, background) -> DeferredRenderOutput:
    """A render's output from its accumulations; the culled rows' NaN mask of ``means2d`` made when first read."""
    if background is not None:
        background = torch.as_tensor(background, dtype=acc.dtype, device=acc.device)
    return DeferredRenderOutput(alpha, None, None, (acc, alpha, background),
                                screen=lambda: (radii, mask_culled(means2d, radii)))


class CpuRenderer(TileRenderer):
    """Compiled CPU tile rasteriser; same images and gradients as :class:`TorchRenderer` up to float32 rounding."""

    name = "cpu"

    def __init__(self, device="cpu", block: int | None = None):
        """``block``: pixels per SIMD block of the compositing kernels (8 or 16); default: the one chosen for the
        CPU numba compiles for (:func:`._cpu_kernels.default_block`). Every choice gives the same images."""
        super().__init__(device)
        self.block = block
        if self.device.type != "cpu":
            raise ValueError(f"the 'cpu' renderer runs on the CPU only, not on {self.device}")

    def render(self, means, quats, scales, opacities, colors, camera: Camera, T_world_cam,
               background: torch.Tensor | None = None, sh_degree: int | None = None,
               low_pass: float = EPS2D) -> RenderOutput:
        """means [N, 3], quats [N, 4] wxyz, scales [N, 3] metres, opacities [N] in (0, 1), colors [N, 3] RGB or
        [N, K, 3] SH coefficients (evaluated in torch from the camera centre, as :class:`.base.TileRenderer`)."""
        colors = view_colors(colors, means, T_world_cam, sh_degree)
        _check_shapes(means, quats, scales, opacities, colors)
        warmup()
        proj = project_cpu(means, quats, scales, camera, T_world_cam, low_pass)
        offsets, flat, tiles_x = bin_tiles_csr(proj, camera.width, camera.height)
        acc, alpha_acc = self._accumulate(proj, opacities, colors, offsets, flat, tiles_x, camera.width,
                                          camera.height, self.block)
        return _output(acc, alpha_acc, proj.radii, proj.means2d, background)

    def render_training(self, means, quats, scales, opacities, colors, camera: Camera, T_world_cam,
                        background: torch.Tensor | None = None, low_pass: float = EPS2D) -> RenderOutput:
        """:meth:`render` of float32 RGB Gaussians (colors [N, 3]) for one training update, without autograd: the
        output's ``training_pass`` (:class:`TrainingPass`) returns the inputs' gradients from those of the
        accumulations (``raw``). The same images and gradients, bit for bit."""
        _check_shapes(means, quats, scales, opacities, colors)
        arrays = [t.detach() for t in (means, quats, scales, opacities, colors)]
        if any(t.dtype != torch.float32 or not t.is_contiguous() for t in arrays):
            raise ValueError("cpu renderer: a training pass takes contiguous float32 tensors")
        tp = TrainingPass(*(t.numpy() for t in arrays), camera, T_world_cam, low_pass, self.block)
        out = _output(*tp.forward(), background)
        out.training_pass = tp
        return out

    def composite(self, proj: Projection, opacities, colors, bins: TileBins, width: int, height: int):
        warmup()
        offsets, flat = tile_lists(bins)
        acc, alpha = self._accumulate(proj, opacities, colors, offsets, flat, bins.tiles_x, width, height, self.block)
        return acc[..., :3], acc[..., 3], alpha

    @staticmethod
    def _accumulate(proj, opacities, colors, offsets, flat, tiles_x, width, height, block=None):
        """(accumulated colour and depth [H, W, 4], alpha [H, W])."""
        order = tile_order(offsets)
        feats = torch.cat([colors, as_dtype(proj.depths[:, None], colors.dtype)], -1)  # [N, 4]
        return _Composite.apply(proj.means2d, proj.conics, opacities, feats, offsets, flat, order, tiles_x, width,
                                height, block)
