"""``cpu`` renderer: the reference's math (projection, tile binning, compositing) in compiled numba kernels.

Three steps, each the reference's twin and each tested against it:
- projection (:mod:`._cpu_projection`): EWA covariance, Jacobian clamp, conic, radius and culling, per Gaussian, with
  a hand-written backward pass, as a ``torch.autograd.Function`` (the torch version costs ~40% of a 160x120 render);
- tile binning (:func:`bin_tiles_csr`): the reference's per-tile, front-to-back lists, compressed instead of padded;
- compositing (:mod:`._cpu_forward`, :mod:`._cpu_backward`, shared parts in :mod:`._cpu_kernels`): forward and
  backward kernels, as a ``torch.autograd.Function``; the forward's gathered tiles, which the backward reads, live
  in tables reused from render to render (:mod:`.scratch`).
The kernels run in parallel on the threads numba may use (``NUMBA_NUM_THREADS`` / ``numba.set_num_threads``).
Float32 throughout; inputs of other dtypes are cast and the gradients cast back. Background and depth
normalisation stay in torch (:func:`.base.finish`), shared with every backend, and run when a render's colour or
depth is first read (:class:`.base.DeferredRenderOutput`: a training update's fused loss reads the accumulations).

The first use in a process loads the compiled kernels from numba's on-disk cache (~1 s), or compiles them when
there is none yet (~15 s on a 2-core machine); :func:`warmup` does this explicitly and reports the time.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ..core.camera import Camera
from .base import DeferredRenderOutput, RenderOutput, TileRenderer, mask_culled, view_colors
from .projection import EPS2D, NEAR, TILE, Projection, TileBins, world_to_cam_np

_warm_seconds: float | None = None


def _kernels():
    """Import (and so JIT-load) the kernels lazily: ``import eligsir_o3d.render`` must not pay numba's start-up."""
    from . import _cpu_kernels
    return _cpu_kernels


_made: dict = {}  # block pixels -> (forward, backward) compositing kernels


def _compositors(block: int | None = None):
    """(forward, backward) compositing kernels for blocks of ``block`` pixels (default: the target's
    :func:`._cpu_kernels.default_block`); the two kernel modules build on the shared helpers of ``_cpu_kernels``."""
    from . import _cpu_backward, _cpu_forward

    k = _kernels()
    block = k.default_block() if block is None else block
    if block not in _made:
        bw, bh = k.BLOCKS[block]
        _made[block] = (_cpu_forward.make(bw, bh), _cpu_backward.make(bw, bh))
    return _made[block]


_pool = None


def _gather_pool():
    """The reused gather tables of the compositing kernels (:mod:`.scratch`)."""
    global _pool
    if _pool is None:
        from .scratch import ScratchPool
        _pool = ScratchPool(_kernels().GATHER_DTYPES)
    return _pool


def _binning():
    from . import _cpu_binning
    return _cpu_binning


def _proj_kernels():
    from . import _cpu_projection
    return _cpu_projection


def _jit():
    from ..runtime import jit  # numba loads with the kernels, not with eligsir_o3d.render
    return jit


def _rows_threads(rows: int, key: str):
    return _jit().rows_threads(rows, key)


def warmup() -> float:
    """Compile (or load from numba's cache) both kernels on a tiny problem; returns the seconds it took.

    Called on a renderer's first use; benchmarks call it to report the first-call cost separately.
    """
    global _warm_seconds
    if _warm_seconds is None:
        t0 = time.perf_counter()
        k = _kernels()
        f32 = np.float32
        means2d = np.array([[3.0, 4.0]], f32)
        conics = np.array([[0.5, 0.0, 0.5]], f32)
        opac = np.array([0.5], f32)
        feats = np.ones((1, 4), f32)
        offsets = np.array([0, 1], np.int64)
        ids = np.zeros(1, np.int64)
        order = np.zeros(1, np.int64)
        h, w = 8, 8
        out_f, out_a = np.empty((h, w, 4), f32), np.empty((h, w), f32)
        out_T, out_last = np.empty((h, w), f32), np.empty((h, w), np.int32)
        bounds = np.empty((1, 3), f32)
        _binning().bin_tiles_fill(means2d, np.array([2], np.int32), np.zeros(1, np.int64), 1, 1, 1)
        k.cull_bounds(conics, opac, bounds)
        forward, backward = _compositors()
        gathered = k.gather_buffers(1, 1, k.default_block())
        k.run(forward, means2d, conics, opac, feats, bounds, offsets, ids, order, 1, 1, w, h,
              out_f, out_a, out_T, out_last, *gathered)
        k.run(backward, *gathered, offsets, ids, order, 1, 1, w, h, out_T, out_last, np.ones((h, w, 4), f32),
              np.ones((h, w), f32), np.empty((1, k.ISECT_COLS), f32), np.empty((1, 10), f32))
        pk = _proj_kernels()
        V, cam = np.eye(4), np.array([5.0, 5.0, 4.0, 4.0, 8, 8, NEAR, EPS2D])
        means = np.array([[0.0, 0.0, 2.0]], f32)
        quats, scales = np.array([[1.0, 0, 0, 0]], f32), np.full((1, 3), 0.1, f32)
        radii = np.empty(1, np.int32)
        pk.project_forward(means, quats, scales, V, cam, means2d, conics, opac, radii)
        pk.project_backward(means, quats, scales, V, cam, means2d, conics, opac, means.copy(), quats.copy(),
                            scales.copy())
        _warm_seconds = time.perf_counter() - t0
    return _warm_seconds


def _f32(x: torch.Tensor) -> torch.Tensor:
    x = x.detach()
    if x.dtype != torch.float32:
        x = x.to(torch.float32)
    return x if x.is_contiguous() else x.contiguous()


def _as(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``x.to(dtype)`` without the operator where it is already of that dtype."""
    return x if x.dtype == dtype else x.to(dtype)


class _Composite(torch.autograd.Function):
    """(means2d [N,2], conics [N,3], opacities [N], feats [N,4] rgb+depth) -> (accumulated feats [H,W,4], alpha [H,W])."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, offsets, flat_ids, order, tiles_x, width, height, block):
        k = _kernels()
        forward, _ = _compositors(block)
        m, c, o, f = _f32(means2d), _f32(conics), _f32(opacities), _f32(feats)
        n_feat = f.shape[1]
        bounds = torch.empty(m.shape[0], 3, dtype=torch.float32)
        with _rows_threads(m.shape[0], "cull_bounds"):
            k.cull_bounds(c.numpy(), o.numpy(), bounds.numpy())
        out_feats = torch.empty(height, width, n_feat, dtype=torch.float32)
        out_alpha = torch.empty(height, width, dtype=torch.float32)
        out_T = torch.empty(height, width, dtype=torch.float32)
        out_last = torch.empty(height, width, dtype=torch.int32)
        gathered = _gather_pool().take(*k.gather_shapes(flat_ids.shape[0], offsets.shape[0] - 1,
                                                        block or k.default_block()))
        k.run(forward, m.numpy(), c.numpy(), o.numpy(), f.numpy(), bounds.numpy(), offsets.numpy(),
              flat_ids.numpy(), order.numpy(), k.task_slots(order.shape[0]), tiles_x, width, height,
              out_feats.numpy(), out_alpha.numpy(), out_T.numpy(), out_last.numpy(), *gathered)
        ctx.save_for_backward(offsets, flat_ids, order, out_T, out_last)
        ctx.gathered = gathered  # the tiles as the forward kernel gathered them, for the backward kernel
        ctx.meta = (tiles_x, width, height, f.shape, [means2d.dtype, conics.dtype, opacities.dtype, feats.dtype], block)
        return _as(out_feats, feats.dtype), _as(out_alpha, feats.dtype)

    @staticmethod
    def backward(ctx, grad_feats, grad_alpha):
        k = _kernels()
        offsets, flat_ids, order, out_T, out_last = ctx.saved_tensors
        tiles_x, width, height, (n, n_feat), dtypes, block = ctx.meta
        if grad_feats is None:
            grad_feats = torch.zeros(height, width, n_feat)
        if grad_alpha is None:
            grad_alpha = torch.zeros(height, width)
        v_isect = torch.empty(flat_ids.shape[0], k.ISECT_COLS, dtype=torch.float32)
        v = torch.empty(n, 6 + n_feat, dtype=torch.float32)
        k.run(_compositors(block)[1], *ctx.gathered, offsets.numpy(), flat_ids.numpy(), order.numpy(),
              k.task_slots(order.shape[0]), tiles_x, width, height, out_T.numpy(), out_last.numpy(),
              _f32(grad_feats).numpy(), _f32(grad_alpha).numpy(), v_isect.numpy(), v.numpy())
        grads = (v[:, 0:2], v[:, 2:5], v[:, 5], v[:, 6:])
        grads = tuple(_as(g, dt) for g, dt in zip(grads, dtypes))
        return grads + (None,) * 7


class _Project(torch.autograd.Function):
    """(means [N,3], quats [N,4], scales [N,3]) -> (means2d [N,2], conics [N,3], depths [N], radii [N] int32)."""

    @staticmethod
    def forward(ctx, means, quats, scales, V, cam):
        pk = _proj_kernels()
        m, q, s = _f32(means), _f32(quats), _f32(scales)
        n = m.shape[0]
        means2d, conics = torch.empty(n, 2), torch.empty(n, 3)
        depths, radii = torch.empty(n), torch.empty(n, dtype=torch.int32)
        with _rows_threads(n, "project_forward"):
            pk.project_forward(m.numpy(), q.numpy(), s.numpy(), V, cam, means2d.numpy(), conics.numpy(),
                               depths.numpy(), radii.numpy())
        ctx.save_for_backward(m, q, s)
        ctx.V, ctx.cam, ctx.dtypes = V, cam, (means.dtype, quats.dtype, scales.dtype)
        ctx.mark_non_differentiable(radii)
        dt = means.dtype
        return _as(means2d, dt), _as(conics, dt), _as(depths, dt), radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii):
        pk = _proj_kernels()
        m, q, s = ctx.saved_tensors
        n = m.shape[0]
        grads = [g if g is not None else torch.zeros(shape) for g, shape in
                 ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_depths, (n,)))]
        v_means, v_quats, v_scales = torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3)
        with _rows_threads(n, "project_backward"):
            pk.project_backward(m.numpy(), q.numpy(), s.numpy(), ctx.V, ctx.cam, *(_f32(g).numpy() for g in grads),
                                v_means.numpy(), v_quats.numpy(), v_scales.numpy())
        return tuple(_as(v, dt) for v, dt in zip((v_means, v_quats, v_scales), ctx.dtypes)) + (None, None)


def project_cpu(means, quats, scales, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> Projection:
    """:func:`.projection.project` in compiled code (forward and backward); same values up to float32 rounding."""
    # the reference rounds the world-to-camera matrix to the parameters' dtype: do the same
    V = world_to_cam_np(T_world_cam, rounded=True)
    cam = np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, NEAR, low_pass],
                   np.float64)
    means2d, conics, depths, radii = _Project.apply(means, quats, scales, V, cam)
    return Projection(means2d, conics, depths, radii)


def tile_lists(bins: TileBins) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded per-tile ids [T, K] -> (offsets [T + 1], flat ids [M]), int64."""
    ids = bins.ids.cpu()
    valid = ids >= 0
    offsets = torch.zeros(ids.shape[0] + 1, dtype=torch.long)
    torch.cumsum(valid.sum(1), 0, out=offsets[1:])
    return offsets, ids[valid].contiguous()


def bin_tiles_csr(proj: Projection, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """:func:`.projection.bin_tiles` in compiled code, as (offsets [T + 1], flat ids [M], tiles_x); same lists."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    radii = _as(proj.radii, torch.int32).numpy()
    depths = _f32(proj.depths).numpy()
    vis = np.flatnonzero(radii > 0)
    # Front to back with ties by index, as the reference's stable sorts, from one fast unstable sort of unique
    # keys: visible depths are > 0, where float32 bit patterns order like the values.
    keys = (depths[vis].view(np.int32).astype(np.int64) << 32) | vis
    keys.sort()
    by_depth = keys & 0xFFFFFFFF
    k = _kernels()
    # in parallel parts where the per-Gaussian kernels run parallel (77k: 2.8 ms on one thread), else in one
    with _rows_threads(vis.shape[0], "bin_tiles") as parallel:
        chunks = k.task_slots(vis.shape[0]) if parallel else 1
        offsets, flat = _binning().bin_tiles_fill(_f32(proj.means2d).numpy(), radii, by_depth, tiles_x, tiles_y,
                                                  chunks)
    return torch.from_numpy(offsets), torch.from_numpy(flat), tiles_x


def _check_shapes(means, quats, scales, opacities, colors) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    want = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
            "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    for name, (t, shape) in want.items():
        if tuple(t.shape) != shape or t.device.type != "cpu":
            raise ValueError(f"cpu renderer: {name} must be a CPU tensor of shape {list(shape)} with N = "
                             f"{n} (from means), got {list(t.shape)} on {t.device}")


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
        if background is not None:
            background = torch.as_tensor(background, dtype=acc.dtype, device=acc.device)
        radii, means2d = proj.radii, proj.means2d  # the culled rows' NaN mask made when first read
        return DeferredRenderOutput(alpha_acc, None, None, (acc, alpha_acc, background),
                                    screen=lambda: (radii, mask_culled(means2d, radii)))

    def composite(self, proj: Projection, opacities, colors, bins: TileBins, width: int, height: int):
        warmup()
        offsets, flat = tile_lists(bins)
        acc, alpha = self._accumulate(proj, opacities, colors, offsets, flat, bins.tiles_x, width, height, self.block)
        return acc[..., :3], acc[..., 3], alpha

    @staticmethod
    def _accumulate(proj, opacities, colors, offsets, flat, tiles_x, width, height, block=None):
        """(accumulated colour and depth [H, W, 4], alpha [H, W])."""
        order = torch.argsort(offsets[1:] - offsets[:-1], descending=True, stable=True)  # heaviest tiles first
        feats = torch.cat([colors, _as(proj.depths[:, None], colors.dtype)], -1)  # [N, 4]
        return _Composite.apply(proj.means2d, proj.conics, opacities, feats, offsets, flat, order, tiles_x, width,
                                height, block)
