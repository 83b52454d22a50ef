"""Depth-derived Gaussian seeds: back-project a strided subset of depth pixels into world-space Gaussians."""

from __future__ import annotations

import torch

from ..camera import Camera


def seeds_from_depth(color: torch.Tensor, depth: torch.Tensor, camera: Camera, T_world_cam, mask: torch.Tensor,
                     stride: int, max_points: int, generator: torch.Generator | None = None,
                     footprint: float = 0.5):
    """Seeds at masked, valid depth pixels on a ``stride`` grid (at most ``max_points``, chosen at random).

    color [H, W, 3], depth [H, W] metres, mask [H, W] bool. Returns (means [M, 3] world, rgbs [M, 3], scales [M]):
    each seed's scale (standard deviation, metres) is ``footprint`` times the width of a stride x stride pixel block
    at its depth: at 0.5 the 2-sigma extents of neighbouring seeds just touch, so the seeds cover the surface.
    """
    sel = torch.zeros_like(mask)
    sel[stride // 2::stride, stride // 2::stride] = True
    sel &= mask & (depth > 0)
    vs, us = torch.nonzero(sel, as_tuple=True)
    if vs.numel() > max_points:
        pick = torch.randperm(vs.numel(), generator=generator, device=vs.device)[:max_points] if generator is None \
            else torch.randperm(vs.numel(), generator=generator)[:max_points].to(vs.device)
        vs, us = vs[pick], us[pick]
    z = depth[vs, us]
    means = camera.unproject(us, vs, z, T_world_cam)
    scales = z * stride / (0.5 * (camera.fx + camera.fy)) * footprint
    return means, color[vs, us], scales
