"""A CPU stand-in for the five CUDA ops that ``gsplat.rasterization`` (1.5.3) calls, built from gsplat's own pure-torch
twins in ``gsplat/cuda/_torch_impl.py`` plus the rules of its CUDA kernels that those twins leave out.

:func:`patch` puts them into ``gsplat.rendering`` in place of the CUDA wrappers, so that gsplat's real Python
``rasterization`` (argument checks, SH evaluation from ``inverse(viewmats)``, "RGB+D" channel stacking, ``meta``)
runs on the CPU, and the project's :class:`GsplatRenderer` conversions are tested against gsplat's conventions rather
than against the project's own projection.

What comes from where:
- projection: ``_quat_scale_to_covar_preci``, ``_world_to_cam``, ``_persp_proj`` (gsplat's Jacobian and its clamp,
  with gsplat's half-integer principal point); then, as in ``ProjectionEWA3DGSFused.cu``: cull at ``z < near`` or
  ``z > far``, add ``eps2d`` to the 2D covariance, cull ``det <= 0``, cull opacity < 1/255, per-axis radii
  ``ceil(min(3.33, sqrt(2 ln(255 o))) sqrt(cov_ii))``, cull boxes off the image; culled rows of means2d, depths and
  conics hold finite garbage (the kernel leaves them uninitialised);
- tile binning: ``_isect_tiles`` and ``_isect_offset_encode`` as they are (depth bits as the sort key);
- compositing (``RasterizeToPixels3DGSFwd.cu``): pixel centres at +0.5, ``alpha = min(0.999, o exp(-sigma))``,
  skipped when ``sigma < 0`` or ``alpha < 1/255``, stop before the transmittance falls to 1e-4 (exclusive),
  ``render_alphas = 1 - T``; gradients by autograd (``_torch_impl``'s own compositor needs nerfacc and CUDA);
- SH: ``_spherical_harmonics`` (masked rows garbage: the kernel leaves them uninitialised).
"""

from __future__ import annotations

import math

import torch

ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat/cuda/include/Common.h


def _impl():
    from gsplat.cuda import _torch_impl

    return _torch_impl


def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01,
                           far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False,
                           calc_compensations=False, camera_model="pinhole", opacities=None):
    assert not packed and not sparse_grad and not calc_compensations and camera_model == "pinhole"
    assert covars is None and means.dim() == 2, "the stand-in covers unbatched quats/scales input"
    impl = _impl()
    covars3d, _ = impl._quat_scale_to_covar_preci(quats, scales, compute_preci=False)  # [N, 3, 3]
    means_c, covars_c = impl._world_to_cam(means, covars3d, viewmats)  # [C, N, 3], [C, N, 3, 3]
    z = means_c[..., 2]
    in_range = (z >= near_plane) & (z <= far_plane)
    # the kernel returns before projecting these: keep their (unused) arithmetic finite for autograd
    safe_c = torch.where(in_range[..., None], means_c, torch.tensor([0.0, 0.0, 1.0], dtype=means.dtype))
    means2d, cov2d = impl._persp_proj(safe_c, covars_c, Ks, width, height)
    cov2d = cov2d + eps2d * torch.eye(2, dtype=means.dtype)
    a, b, c = cov2d[..., 0, 0], 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0]), cov2d[..., 1, 1]
    det = a * c - b * b
    ok = in_range & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    with torch.no_grad():
        extend = torch.full_like(z, 3.33)
        if opacities is not None:
            o = opacities.detach()[None].expand_as(z)
            ok = ok & (o >= ALPHA_THRESHOLD)
            extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log((o / ALPHA_THRESHOLD).clamp_min(1.0))))
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c.detach().clamp_min(0)))
        ok = ok & ~((rx <= radius_clip) & (ry <= radius_clip))
        m = means2d.detach()
        ok = ok & ~((m[..., 0] + rx <= 0) | (m[..., 0] - rx >= width) | (m[..., 1] + ry <= 0) |
                    (m[..., 1] - ry >= height))
        radii = torch.where(ok[..., None], torch.stack([rx, ry], -1), torch.zeros_like(m)).to(torch.int32)
    means2d = torch.where(ok[..., None], means2d, _garbage(means2d))
    conics = torch.where(ok[..., None], conics, _garbage(conics))
    depths = torch.where(ok, z, _garbage(z))
    return radii, means2d, depths, conics, None


def _garbage(like: torch.Tensor) -> torch.Tensor:
    """What an uninitialised CUDA buffer may hold: plausible-looking finite numbers."""
    return torch.empty_like(like).uniform_(-1e3, 1e3, generator=torch.Generator().manual_seed(like.numel()))


def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, segmented=False, packed=False,
                n_images=None, image_ids=None, gaussian_ids=None):
    assert not packed and not segmented
    return _impl()._isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=sort)


def isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
    return _impl()._isect_offset_encode(isect_ids, n_images, tile_width, tile_height)


def spherical_harmonics(degrees_to_use, dirs, coeffs, masks=None):
    colors = _impl()._spherical_harmonics(degrees_to_use, dirs, coeffs)
    if masks is not None:
        colors = torch.where(masks[..., None], colors, _garbage(colors))
    return colors


def rasterize_to_pixels(means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets,
                        flatten_ids, backgrounds=None, masks=None, packed=False, absgrad=False):
    """Front-to-back compositing of each tile's depth-sorted list, per pixel, with the forward kernel's rules."""
    assert not packed and masks is None
    image_dims = means2d.shape[:-2]
    n, channels = means2d.shape[-2], colors.shape[-1]
    n_images = math.prod(image_dims)
    tiles_y, tiles_x = isect_offsets.shape[-2:]
    flat_m, flat_c = means2d.reshape(-1, 2), conics.reshape(-1, 3)
    flat_o, flat_f = opacities.reshape(-1), colors.reshape(-1, channels)
    offsets = isect_offsets.reshape(-1).tolist() + [flatten_ids.numel()]
    ids_all = flatten_ids.long()
    images, alpha_images = [], []
    for img in range(n_images):
        rows, alpha_rows = [], []
        for ty in range(tiles_y):
            row, alpha_row = [], []
            for tx in range(tiles_x):
                t = (img * tiles_y + ty) * tiles_x + tx
                ids = ids_all[offsets[t]:offsets[t + 1]]  # [K], front to back
                ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, image_height), dtype=means2d.dtype)
                xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, image_width), dtype=means2d.dtype)
                py, px = torch.meshgrid(ys + 0.5, xs + 0.5, indexing="ij")  # gsplat's pixel centres
                pix = torch.stack([px.reshape(-1), py.reshape(-1)], -1)  # [P, 2]
                acc, alpha = _composite(pix, flat_m[ids], flat_c[ids], flat_o[ids], flat_f[ids])
                if backgrounds is not None:
                    acc = acc + (1.0 - alpha)[:, None] * backgrounds.reshape(n_images, channels)[img]
                row.append(acc.reshape(len(ys), len(xs), channels))
                alpha_row.append(alpha.reshape(len(ys), len(xs), 1))
            rows.append(torch.cat(row, 1))
            alpha_rows.append(torch.cat(alpha_row, 1))
        images.append(torch.cat(rows, 0))
        alpha_images.append(torch.cat(alpha_rows, 0))
    render_colors = torch.stack(images).reshape(image_dims + (image_height, image_width, channels))
    render_alphas = torch.stack(alpha_images).reshape(image_dims + (image_height, image_width, 1))
    return render_colors, render_alphas


def _composite(pix, m, con, o, feats):
    """pix [P, 2]; m [K, 2], con [K, 3], o [K], feats [K, D] front to back -> ([P, D], alpha [P])."""
    if m.shape[0] == 0:
        return feats.new_zeros(pix.shape[0], feats.shape[1]), pix.new_zeros(pix.shape[0])
    dx = m[None, :, 0] - pix[:, None, 0]  # [P, K]
    dy = m[None, :, 1] - pix[:, None, 1]
    sigma = 0.5 * (con[None, :, 0] * dx * dx + con[None, :, 2] * dy * dy) + con[None, :, 1] * dx * dy
    alpha = torch.clamp_max(o[None] * torch.exp(-sigma), 0.999)
    alpha = torch.where((sigma < 0) | (alpha < ALPHA_THRESHOLD), torch.zeros_like(alpha), alpha)
    T_after = torch.cumprod(1.0 - alpha, -1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], -1)
    used = T_after > 1e-4  # the kernel stops at the first Gaussian that would take T to 1e-4 or below
    w = torch.where(used, alpha * T_before, torch.zeros_like(alpha))
    T_final = torch.where(used, 1.0 - alpha, torch.ones_like(alpha)).prod(-1)  # T after the last one used
    return w @ feats, 1.0 - T_final


def patch(monkeypatch):
    """Put the stand-ins into ``gsplat.rendering``; returns gsplat's (now CPU-runnable) ``rasterization``."""
    import gsplat.rendering as rendering

    for name in ("fully_fused_projection", "isect_tiles", "isect_offset_encode", "rasterize_to_pixels",
                 "spherical_harmonics"):
        monkeypatch.setattr(rendering, name, globals()[name])
    return rendering.rasterization
