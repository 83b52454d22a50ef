"""Pure-PyTorch reference compositor: readable, differentiable by autograd, any device.

Every other backend is tested against this one. Memory stays bounded by processing tiles in chunks so that one
chunk's [tiles, 256 pixels, K Gaussians] working set stays under ``max_elements``.
"""

from __future__ import annotations

import torch

from .base import ALPHA_MAX, ALPHA_MIN, T_MIN, TileRenderer, tile_pixel_coords, untile
from .projection import Projection, TileBins


class TorchRenderer(TileRenderer):
    name = "torch"

    def __init__(self, device="cpu", max_elements: int = 1 << 23):
        super().__init__(device)
        self.max_elements = max_elements

    def composite(self, proj: Projection, opacities, colors, bins: TileBins, width: int, height: int):
        n_tiles, k_max = bins.ids.shape
        device = proj.means2d.device
        pix = tile_pixel_coords(bins, device)  # [T, P, 2]
        n_pix = pix.shape[1]
        feats = torch.cat([colors, proj.depths[:, None]], -1)  # [N, 4]
        out = torch.zeros(n_tiles, n_pix, 5, device=device, dtype=colors.dtype)
        if k_max > 0:
            # Group tiles of similar list length so the padding to a chunk's longest list stays small.
            counts = (bins.ids >= 0).sum(1)
            order = torch.argsort(counts)
            s = 0
            while s < n_tiles:
                k = max(1, int(counts[order[min(n_tiles - 1, s)]]))
                # grow the chunk while the longest list in it keeps the working set under budget
                e = s + 1
                while e < n_tiles and (e - s + 1) * n_pix * max(k, int(counts[order[e]])) <= self.max_elements:
                    k = max(k, int(counts[order[e]]))
                    e += 1
                sel = order[s:e]
                if k > 0 and int(counts[sel].max()) > 0:
                    out = out.index_put((sel,), self._tiles(proj, opacities, feats, bins.ids[sel, :k], pix[sel]))
                s = e
        img = untile(out, bins, width, height)
        return img[..., :3], img[..., 3], img[..., 4]

    @staticmethod
    def _tiles(proj: Projection, opacities, feats, ids, pix):
        """Blend one chunk of tiles: ids [t, K], pix [t, P, 2] -> [t, P, 5] (rgb, depth, alpha) accumulations."""
        valid = ids >= 0  # [t, K]
        safe = ids.clamp_min(0)
        mu = proj.means2d[safe]  # [t, K, 2]
        con = proj.conics[safe]  # [t, K, 3]
        op = opacities[safe]  # [t, K]
        d = pix[:, :, None, :] - mu[:, None, :, :]  # [t, P, K, 2]
        dx, dy = d[..., 0], d[..., 1]
        sigma = 0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) + con[:, None, :, 1] * dx * dy
        alpha = torch.clamp(op[:, None, :] * torch.exp(-sigma), max=ALPHA_MAX)
        keep = valid[:, None, :] & (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        # Front-to-back transmittance; a Gaussian is blended only while the transmittance after it stays > T_MIN.
        T_after = torch.cumprod(1.0 - alpha, dim=-1)
        T_before = torch.cat([torch.ones_like(T_after[..., :1]), T_after[..., :-1]], -1)
        w = alpha * T_before * (T_after > T_MIN).to(alpha.dtype)  # [t, P, K]
        f = feats[safe]  # [t, K, 4]
        acc = torch.einsum("tpk,tkc->tpc", w, f)
        return torch.cat([acc, w.sum(-1, keepdim=True)], -1)
