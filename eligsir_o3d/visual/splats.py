"""Gaussians as a viewer draws them: centres, 3x3 covariances, colours and opacities, from a map or a PLY.

Any standard 3DGS PLY works (this package's, gsplat's, the original 3DGS code's): SH degree 0-3, only the DC
term is used for colour (a browser splat renderer draws one colour per Gaussian; the view-dependent f_rest terms
are ignored, which is what SuperSplat's and viser's plain splat modes do too).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core.gaussians import GaussianMap, sh0_to_rgb
from ..render.projection import quat_to_rotmat


@dataclass
class Splats:
    centers: np.ndarray  # [N, 3] float32, metres
    covariances: np.ndarray  # [N, 3, 3] float32, metres^2
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1] (SH DC term)
    opacities: np.ndarray  # [N, 1] float32 in [0, 1]
    sh_degree: int = 0

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    def bounds(self, lo_pct: float = 2.0, hi_pct: float = 98.0) -> tuple[np.ndarray, np.ndarray]:
        """Robust axis-aligned bounds of the centres (percentiles, so that floaters do not stretch them)."""
        if len(self) == 0:
            return np.zeros(3), np.zeros(3)
        return np.percentile(self.centers, lo_pct, axis=0), np.percentile(self.centers, hi_pct, axis=0)


@torch.no_grad()
def splats_from_map(gmap: GaussianMap, min_opacity: float = 0.0) -> Splats:
    """Viewer arrays of a :class:`GaussianMap` (covariance R diag(s^2) R^T; colour from the SH DC term)."""
    keep = gmap.opacities.detach() >= min_opacity  # [N]
    means = gmap.means.detach()[keep].float().cpu()  # [M, 3]
    scales = gmap.scales.detach()[keep].float().cpu()  # [M, 3]
    R = quat_to_rotmat(gmap.quats.detach()[keep].float().cpu())  # [M, 3, 3]
    cov = (R * scales[:, None, :] ** 2) @ R.transpose(1, 2)  # [M, 3, 3]
    rgb = sh0_to_rgb(gmap.params["sh0"].detach()[keep, 0].float().cpu()).clamp(0.0, 1.0)  # [M, 3]
    opac = gmap.opacities.detach()[keep].float().cpu()[:, None]  # [M, 1]
    return Splats(means.numpy(), cov.numpy(), rgb.numpy(), opac.numpy(), gmap.sh_degree)


def read_splats(path: str | Path, min_opacity: float = 0.0, bake: bool = True) -> Splats:
    """Viewer arrays of a 3DGS PLY file; raises :class:`eligsir_o3d.io.ply.PlyError` naming the file on bad input.

    A browser splat renderer adds 3DGS's fixed 0.3 px^2, so with ``bake`` a map supervised coarser than its
    camera (``run.json`` and ``trajectory.txt`` beside it: a results folder) gets its low-pass baked in
    (:func:`eligsir_o3d.export.viewers.baked_for_viewers`), as the web formats do; other PLYs are drawn as they are."""
    from ..io.ply import PlyError, load_ply

    path = Path(path)
    gmap = load_ply(path, "cpu")
    if len(gmap) == 0:
        raise PlyError(f"{path}: the map has no Gaussians")
    if bake:
        gmap = _baked_if_known(gmap, path)
    return splats_from_map(gmap, min_opacity)


def _baked_if_known(gmap: GaussianMap, path: Path) -> GaussianMap:
    from ..export.viewers import for_viewers
    from ..export.views import camera_next_to, poses_next_to

    try:
        return for_viewers(gmap, camera_next_to(path), poses_next_to(path))[0]
    except ValueError:  # an unreadable trajectory: the viewer still shows the map as it is
        return gmap
