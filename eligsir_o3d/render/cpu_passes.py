"""The ``cpu`` renderer's compiled passes on float32 arrays: projection, tile binning and compositing, forward and
backward, each a call of its numba kernels (:mod:`._cpu_projection`, :mod:`._cpu_binning`, :mod:`._cpu_forward`,
:mod:`._cpu_backward`), and :class:`TrainingPass`, one training render chained from them without autograd. The
renderer's autograd functions (:mod:`.cpu_backend`) call the same passes, so both give the same bits.

The first use in a process loads the compiled kernels from numba's on-disk cache (~1 s), or compiles them when
there is none yet (~15 s on a 2-core machine); :func:`warmup` does this explicitly and reports the time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ..core.camera import Camera
from .projection import EPS2D, NEAR, TILE, Projection, world_to_cam_np

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


def float32(x: torch.Tensor) -> torch.Tensor:
    """``x`` detached, as a contiguous float32 tensor (no copy where it is one)."""
    x = x.detach()
    if x.dtype != torch.float32:
        x = x.to(torch.float32)
    return x if x.is_contiguous() else x.contiguous()


def as_dtype(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``x.to(dtype)`` without the operator where it is already of that dtype."""
    return x if x.dtype == dtype else x.to(dtype)


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


@dataclass(slots=True)
class Tiles:
    """What the compositing forward leaves for its backward: the tile lists, each pixel's final transmittance and
    last contributor, the tiles as the forward kernel gathered them, and the sizes."""

    offsets: torch.Tensor
    flat_ids: torch.Tensor
    order: torch.Tensor
    out_T: torch.Tensor
    out_last: torch.Tensor
    gathered: tuple
    tiles_x: int
    width: int
    height: int
    n: int
    n_feat: int
    block: int | None


def composite_forward(m, c, o, f, offsets, flat_ids, order, tiles_x, width, height, block):
    """The compositing kernels' forward on float32 arrays (means2d [N, 2], conics [N, 3], opacities [N], feats
    [N, F]): (accumulated feats [H, W, F], alpha [H, W], :class:`Tiles`)."""
    k = _kernels()
    forward, _ = _compositors(block)
    n, n_feat = f.shape
    bounds = np.empty((m.shape[0], 3), np.float32)
    with _rows_threads(m.shape[0], "cull_bounds"):
        k.cull_bounds(c, o, bounds)
    out_feats = torch.empty(height, width, n_feat, dtype=torch.float32)
    out_alpha = torch.empty(height, width, dtype=torch.float32)
    out_T = torch.empty(height, width, dtype=torch.float32)
    out_last = torch.empty(height, width, dtype=torch.int32)
    gathered = _gather_pool().take(*k.gather_shapes(flat_ids.shape[0], offsets.shape[0] - 1,
                                                    block or k.default_block()))
    k.run(forward, m, c, o, f, bounds, offsets.numpy(), flat_ids.numpy(), order.numpy(),
          k.task_slots(order.shape[0]), tiles_x, width, height, out_feats.numpy(), out_alpha.numpy(),
          out_T.numpy(), out_last.numpy(), *gathered)
    tiles = Tiles(offsets=offsets, flat_ids=flat_ids, order=order, out_T=out_T, out_last=out_last,
                   gathered=gathered, tiles_x=tiles_x, width=width, height=height, n=n, n_feat=n_feat, block=block)
    return out_feats, out_alpha, tiles


def composite_backward(t: Tiles, grad_feats: np.ndarray, grad_alpha: np.ndarray) -> torch.Tensor:
    """The compositing kernels' backward from float32 gradients of the accumulations ([H, W, F], [H, W]): per
    Gaussian [N, 6 + F] the gradients of means2d (2), conics (3), opacity (1) and feats (F)."""
    k = _kernels()
    v_isect = torch.empty(t.flat_ids.shape[0], k.ISECT_COLS, dtype=torch.float32)
    v = torch.empty(t.n, 6 + t.n_feat, dtype=torch.float32)
    k.run(_compositors(t.block)[1], *t.gathered, t.offsets.numpy(), t.flat_ids.numpy(), t.order.numpy(),
          k.task_slots(t.order.shape[0]), t.tiles_x, t.width, t.height, t.out_T.numpy(), t.out_last.numpy(),
          grad_feats, grad_alpha, v_isect.numpy(), v.numpy())
    return v


def project_forward(m, q, s, V, cam) -> tuple:
    """The projection kernel on float32 arrays (means [N, 3], quats [N, 4], scales [N, 3]): (means2d [N, 2],
    conics [N, 3], depths [N], radii [N] int32)."""
    n = m.shape[0]
    means2d, conics = torch.empty(n, 2), torch.empty(n, 3)
    depths, radii = torch.empty(n), torch.empty(n, dtype=torch.int32)
    with _rows_threads(n, "project_forward"):
        _proj_kernels().project_forward(m, q, s, V, cam, means2d.numpy(), conics.numpy(), depths.numpy(),
                                        radii.numpy())
    return means2d, conics, depths, radii


def project_backward(m, q, s, V, cam, g_means2d, g_conics, g_depths) -> tuple:
    """The projection's backward on float32 arrays: (means, quats, scales) gradients from those of (means2d,
    conics, depths), each a contiguous array."""
    n = m.shape[0]
    v_means, v_quats, v_scales = torch.empty(n, 3), torch.empty(n, 4), torch.empty(n, 3)
    with _rows_threads(n, "project_backward"):
        _proj_kernels().project_backward(m, q, s, V, cam, g_means2d, g_conics, g_depths, v_means.numpy(),
                                         v_quats.numpy(), v_scales.numpy())
    return v_means, v_quats, v_scales


def view_arrays(camera: Camera, T_world_cam, low_pass: float) -> tuple[np.ndarray, np.ndarray]:
    """(world-to-camera matrix, camera row) as the projection kernels take them; the matrix rounded to float32 as
    the reference rounds it to the parameters' dtype."""
    V = world_to_cam_np(T_world_cam, rounded=True)
    cam = np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, NEAR, low_pass],
                   np.float64)
    return V, cam


def bin_tiles_csr(proj: Projection, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """:func:`.projection.bin_tiles` in compiled code, as (offsets [T + 1], flat ids [M], tiles_x); same lists."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    radii = as_dtype(proj.radii, torch.int32).numpy()
    depths = float32(proj.depths).numpy()
    vis = np.flatnonzero(radii > 0)
    # Front to back with ties by index, as the reference's stable sorts, from one fast unstable sort of unique
    # keys: visible depths are > 0, where float32 bit patterns order like the values.
    keys = (depths[vis].view(np.int32).astype(np.int64) << 32) | vis
    keys.sort()
    by_depth = keys & 0xFFFFFFFF
    k = _kernels()
    # in parallel parts where the per-Gaussian kernels run parallel, else in one
    with _rows_threads(vis.shape[0], "bin_tiles") as parallel:
        chunks = k.task_slots(vis.shape[0]) if parallel else 1
        offsets, flat = _binning().bin_tiles_fill(float32(proj.means2d).numpy(), radii, by_depth, tiles_x, tiles_y,
                                                  chunks)
    return torch.from_numpy(offsets), torch.from_numpy(flat), tiles_x


def tile_order(offsets: torch.Tensor) -> torch.Tensor:
    """The tiles heaviest first (ties in tile order): the compositing kernels' task order."""
    return torch.argsort(offsets[1:] - offsets[:-1], descending=True, stable=True)


class TrainingPass:
    """One training render of float32 RGB Gaussians without autograd: :meth:`forward` draws them and keeps what
    :meth:`backward` needs, which returns the inputs' gradients from those of the accumulations. The same kernels,
    in the same order, as a render through autograd (:meth:`CpuRenderer.render`), so the same bits."""

    def __init__(self, means, quats, scales, opacities, colors, camera: Camera, T_world_cam, low_pass: float,
                 block: int | None = None):
        """means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, 3]: contiguous float32 arrays."""
        self.m, self.q, self.s, self.o, self.colors = means, quats, scales, opacities, colors
        self.camera, self.block = camera, block
        self.V, self.cam = view_arrays(camera, T_world_cam, low_pass)

    def forward(self) -> tuple:
        """(accumulated colour and depth [H, W, 4], alpha [H, W], radii [N], means2d [N, 2])."""
        warmup()
        w, h = self.camera.width, self.camera.height
        means2d, conics, depths, radii = project_forward(self.m, self.q, self.s, self.V, self.cam)
        offsets, flat, tiles_x = bin_tiles_csr(Projection(means2d, conics, depths, radii), w, h)
        feats = np.empty((self.m.shape[0], 4), np.float32)
        feats[:, :3] = self.colors
        feats[:, 3] = depths.numpy()
        acc, alpha, self.tiles = composite_forward(means2d.numpy(), conics.numpy(), self.o, feats, offsets,
                                                    flat, tile_order(offsets), tiles_x, w, h, self.block)
        return acc, alpha, radii, means2d

    def backward(self, grad_acc: torch.Tensor, grad_alpha: torch.Tensor) -> tuple:
        """Gradients (means, quats, scales, opacities, colors) from those of the accumulations (float32 [H, W, 4]
        and [H, W])."""
        v = composite_backward(self.tiles, grad_acc.numpy(), grad_alpha.numpy()).numpy()
        g_means, g_quats, g_scales = project_backward(
            self.m, self.q, self.s, self.V, self.cam, np.ascontiguousarray(v[:, 0:2]),
            np.ascontiguousarray(v[:, 2:5]), np.ascontiguousarray(v[:, 9]))
        return (g_means, g_quats, g_scales, torch.from_numpy(np.ascontiguousarray(v[:, 5])),
                torch.from_numpy(np.ascontiguousarray(v[:, 6:9])))
