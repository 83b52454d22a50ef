"""``gsplat`` renderer: ``gsplat.rasterization`` (1.5.3) on CUDA, with the project's conventions converted here only.

Conventions converted in :meth:`GsplatRenderer.render`:
- pose: ``T_world_cam`` (camera-to-world) -> gsplat's ``viewmats`` (world-to-camera), [1, 4, 4];
- pixels: ours have integer centres (Open3D), gsplat's half-integer ones, so ``Ks`` gets ``cx + 0.5, cy + 0.5`` and
  the returned ``means2d`` get ``-0.5``;
- colour: [N, 3] RGB as is, or [N, K, 3] SH coefficients with ``sh_degree`` passed through: gsplat evaluates them
  in its kernel from the camera centre of ``viewmats`` (same basis and +0.5 / clamp as :mod:`.sh`, tested);
- outputs: ``render_mode="RGB+D"`` gives accumulated colour and accumulated z-depth without background; the
  background and the depth normalisation are then applied by :func:`.base.finish`, as for every other backend;
- radii: gsplat 1.5 returns per-axis radii [C, N, 2]; ours are one radius per Gaussian (the larger axis);
- means2d: gsplat leaves the rows of culled Gaussians uninitialised; they are set to NaN here (see RenderOutput).

gsplat loads its CUDA extension on first use, JIT-compiling it when none is built (minutes, logged; see
:mod:`.availability`); the first render - normally :meth:`Reconstructor.warmup` - pays that.
Its projection differs from the reference in one documented way: gsplat 1.5 bounds each Gaussian by an opacity-aware
box (``min(3.33, sqrt(2 ln(255 o)))`` sigma per axis) where the reference uses a 3-sigma circle, so a Gaussian with
opacity above ~0.35 can reach a few more or fewer pixels at tile borders (each by less than 0.011 in alpha).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from ..core.camera import Camera
from ..core.per_view import PerView
from .availability import gsplat_status, load_gsplat_extension
from .base import DeferredRenderOutput, RenderOutput, finish, mask_culled
from .projection import EPS2D, NEAR, TILE, world_to_cam


def gsplat_intrinsics(camera: Camera, device) -> torch.Tensor:
    """[3, 3] K in gsplat's pixel convention: pixel centres at +0.5, so the principal point moves by half a pixel."""
    return torch.tensor([[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]],
                        dtype=torch.float32, device=device)


class GsplatRenderer:
    """Same interface and outputs as :class:`.base.TileRenderer`, rasterised by gsplat's CUDA kernels.

    ``rasterization``: a stand-in for ``gsplat.rasterization`` with its signature (tests run the conversions on the
    CPU through one); by default gsplat's own, after checking that its CUDA extension can be had.
    """

    name = "gsplat"

    def __init__(self, device="cuda", rasterization: Callable | None = None):
        self.device = torch.device(device)
        self.compile_s = 0.0  # seconds the first render spent JIT-compiling gsplat's extension (0: none needed)
        self._rasterization = rasterization
        self._camera_tensors = PerView(self._make_camera_tensors)  # the views seen recently
        if rasterization is None:
            status = gsplat_status(self.device)
            if not status.usable:
                raise status.error()

    def _load(self) -> Callable:
        if self._rasterization is None:
            self.compile_s = load_gsplat_extension()
            from gsplat import rasterization

            self._rasterization = rasterization
        return self._rasterization

    @staticmethod
    def _make_camera_tensors(camera: Camera, T: np.ndarray, device: str) -> tuple[torch.Tensor, torch.Tensor]:
        """viewmats [1, 4, 4] and Ks [1, 3, 3] on ``device``: made once per view (``self._camera_tensors``), as a
        host-to-device copy from pageable memory waits for the GPU."""
        return world_to_cam(T, device, torch.float32)[None], gsplat_intrinsics(camera, device)[None]

    def render(self, means, quats, scales, opacities, colors, camera: Camera, T_world_cam,
               background: torch.Tensor | None = None, sh_degree: int | None = None,
               low_pass: float = EPS2D) -> RenderOutput:
        """means [N, 3], quats [N, 4] wxyz, scales [N, 3] metres, opacities [N] in (0, 1), colors [N, 3] RGB or
        [N, K, 3] SH coefficients (degree ``sh_degree``, default all that K holds, at most 3)."""
        rasterization = self._load()
        dtype, device = means.dtype, means.device
        if means.shape[0] == 0:  # gsplat's launch for zero Gaussians divides by zero (SIGFPE kills the process)
            return self._empty(camera, background, dtype, device)
        if colors.dim() == 3 and sh_degree is None:
            from .sh import sh_degree_of

            sh_degree = sh_degree_of(colors.shape[1])
        if colors.dim() == 2:
            sh_degree = None
        viewmats, Ks = self._camera_tensors(camera, T_world_cam, str(device))  # [1, 4, 4], [1, 3, 3]
        rendered, alphas, meta = rasterization(
            means.float(), quats.float(), scales.float(), opacities.float(), colors.float(), viewmats, Ks,
            camera.width, camera.height, near_plane=NEAR, eps2d=float(low_pass), radius_clip=0.0, sh_degree=sh_degree,
            packed=False, tile_size=TILE, render_mode="RGB+D", rasterize_mode="classic")
        if background is not None:
            background = torch.as_tensor(background, dtype=dtype, device=device)

        def screen():
            radii = meta["radii"][0]  # [N, 2] in gsplat 1.5 ([N] in older releases)
            if radii.dim() == 2:
                radii = radii.max(dim=-1).values
            radii = radii.to(torch.int32)
            return radii, mask_culled(meta["means2d"][0] - 0.5, radii)  # integer pixel centres, NaN where culled

        # the accumulations as gsplat wrote them (RGB and depth summed, no background): a fused loss reads these;
        # colour, depth, radii and means2d are made when first read
        # (views, so that autograd hands their gradients back without a copy)
        raw = (rendered.squeeze(0).to(dtype), alphas.reshape(alphas.shape[1:3]).to(dtype), background)
        return DeferredRenderOutput(raw[1], None, None, raw, screen=screen)

    @staticmethod
    def _empty(camera: Camera, background, dtype, device) -> RenderOutput:
        """The render of a map with no Gaussians (before the first seeds, or a view that culled every row): the
        background, zero alpha and depth, no radii."""
        zeros = torch.zeros(camera.height, camera.width, dtype=dtype, device=device)
        if background is not None:
            background = torch.as_tensor(background, dtype=dtype, device=device)
        color, depth, alpha = finish(zeros[..., None].expand(-1, -1, 3), zeros, zeros, background)
        return RenderOutput(color, depth, alpha, torch.zeros(0, dtype=torch.int32, device=device),
                            torch.zeros(0, 2, dtype=dtype, device=device))
