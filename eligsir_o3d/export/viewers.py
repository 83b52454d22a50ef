"""A map for viewers with 3DGS's fixed low-pass: the low-pass of the resolution the map was supervised at, baked in.

This package draws a map finer than it was supervised with a wider screen-space low-pass
(:meth:`.GaussianMap.low_pass`: 4.8 px^2 at full size for a map fitted at 1/4 scale); other 3DGS viewers, SPZ and
``.splat`` players always add 0.3 px^2, so they show its Gaussians eroded. :func:`baked_for_viewers` widens each
Gaussian in 3D by the extra low-pass at its depth instead (Mip-Splatting's 3D filter, without its opacity
compensation, which these maps were not trained with): at the depth of the nearest given view that sees it, the
extra (low_pass - 0.3) px^2 is (low_pass - 0.3) z^2 / (fx fy) m^2 of isotropic variance. The result records full
resolution as its supervision, so this package then draws it with 0.3 px^2 as well.

    shown, low_pass = for_viewers(rec.gmap, rec.camera, poses)     # the map itself where there is nothing to bake
    write_for_viewers("runs/kitchen/map.ply", "runs/kitchen/map_viewers.ply")   # `eligsir export --for-viewers`

The web formats (:mod:`.web`) bake the same way before they write.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, GaussianMap
from ..render.projection import NEAR


def nearest_depths(means: np.ndarray, camera: Camera, poses: Sequence[np.ndarray]) -> np.ndarray:
    """Per point [N, 3]: its smallest depth in the views (camera-to-world ``poses``) whose image it falls in; for
    a point no view sees, its distance to the nearest camera centre. [N] float64 metres."""
    best = np.full(len(means), np.inf)
    centre_dist = np.full(len(means), np.inf)
    for T in poses:
        T = np.asarray(T, np.float64)
        p = (means - T[:3, 3]) @ T[:3, :3]  # world -> camera: R^T (x - t)
        z = p[:, 2]
        zs = np.where(z > NEAR, z, 1.0)
        u, v = camera.fx * p[:, 0] / zs + camera.cx, camera.fy * p[:, 1] / zs + camera.cy
        seen = (z > NEAR) & (u > -0.5) & (u < camera.width - 0.5) & (v > -0.5) & (v < camera.height - 0.5)
        best = np.where(seen, np.minimum(best, z), best)
        centre_dist = np.minimum(centre_dist, np.linalg.norm(means - T[:3, 3], axis=1))
    return np.where(np.isfinite(best), best, centre_dist)


@torch.no_grad()
def baked_for_viewers(gmap: GaussianMap, camera: Camera, poses: Sequence[np.ndarray]) -> GaussianMap:
    """A copy of ``gmap`` that a viewer adding 0.3 px^2 at ``camera``'s resolution draws as this package draws
    ``gmap`` there (see the module docstring); ``poses``: the views it was mapped from (camera-to-world)."""
    if len(poses) == 0:
        raise ValueError("baking the low-pass needs the map's views: no poses given")
    out = GaussianMap(gmap.sh_degree, "cpu")
    out.load_state_dict({"sh_degree": gmap.sh_degree,
                         "params": {n: p.detach().cpu().clone() for n, p in gmap.params.items()}})
    extra = gmap.low_pass(camera) - EPS2D
    if extra > 0 and len(out):
        z = nearest_depths(out.means.double().numpy(), camera, poses)
        var = torch.from_numpy(extra * z * z / (camera.fx * camera.fy)).float()[:, None]  # [N, 1] m^2
        s = out.params["scales"]
        s.copy_(0.5 * torch.log(torch.exp(2.0 * s) + var))
    out.supervision_focal = math.sqrt(camera.fx * camera.fy)
    return out


def for_viewers(gmap: GaussianMap, camera: Camera | None, poses: Sequence[np.ndarray] | None
                ) -> tuple[GaussianMap, float]:
    """(what a 0.3 px^2 viewer should draw, the low-pass baked in): :func:`baked_for_viewers` where ``gmap`` was
    supervised coarser than ``camera`` and ``poses`` are known, else ``gmap`` itself and 0.3 (nothing baked)."""
    lp = gmap.low_pass(camera) if camera is not None else EPS2D
    if lp <= EPS2D or not poses:
        return gmap, EPS2D
    return baked_for_viewers(gmap, camera, list(poses)), lp


def write_for_viewers(map_ply: str | Path, out_ply: str | Path, camera: Camera | None = None,
                      poses: Sequence[np.ndarray] | str | Path | None = None) -> dict:
    """Read ``map_ply``, bake its low-pass for ``camera`` (default: the run's, beside the map) and ``poses``
    (default: trajectory.txt beside the map), write ``out_ply``; returns a summary."""
    from ..io.guards import refuse_overwriting_inputs
    from ..io.ply import load_ply, save_ply
    from .views import camera_next_to, poses_next_to

    map_ply = Path(map_ply)
    refuse_overwriting_inputs({"--for-viewers": out_ply}, {"the map": map_ply})
    if not map_ply.is_file():
        raise ValueError(f"{map_ply}: no such map")
    gmap = load_ply(map_ply)
    camera = camera or camera_next_to(map_ply)
    if camera is None:
        raise ValueError(f"{map_ply}: no camera beside the map (run.json of eligsir map): the low-pass depends on "
                         f"the resolution the map is viewed at")
    poses = poses_next_to(map_ply, poses, required=True)
    lp = gmap.low_pass(camera)
    save_ply(baked_for_viewers(gmap, camera, poses), out_ply)
    return {"for_viewers": str(out_ply), "baked_low_pass_px2": lp, "gaussians": len(gmap)}
