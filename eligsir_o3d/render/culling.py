"""View culling: the Gaussians that can reach a view, so an update projects, composites, steps and noises only those
and its cost follows the Gaussians in view, not the map's total.

:func:`in_view`: the ids of the Gaussians whose screen footprint can reach a camera's image. The test bounds the
renderer's 3-sigma radius from above (the clamped projection Jacobian's Frobenius norm times the largest scale,
plus the low-pass, the radius formula's clamp and rounding), so every Gaussian the renderer would draw is kept and
rendering the kept ones gives the same image and the same gradients as rendering the map (tested against the torch
reference). The kernel sets (:mod:`..kernels`) run it: one compiled pass on a float32 CPU map
(:mod:`._cull_kernels`), torch operators in the reference set, a fused kernel in the device set.

On a large map the test does not read every row: from :data:`.cell_index.MIN_ROWS` rows a float32 CPU map keeps a
spatial index (:class:`.cell_index.CellIndex`, groups of nearby rows with their bounds, told of every row an update,
the noise or relocation changes) and :func:`map_in_view` tests the groups first, then the rows of the groups that
can reach the view: the same ids. Smaller maps take one pass over every row.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import PARAM_NAMES
from .projection import EPS2D, NEAR, world_to_cam_np


def camera_bounds(camera: Camera, low_pass: float = EPS2D) -> np.ndarray:
    """(fx, fy, cx, cy, width, height, near, jb2, lp) float64; jb2 * s^2 / z^2 bounds the largest eigenvalue of the
    projected covariance of a Gaussian of largest scale s at depth z (the Jacobian's x/z, y/z clamped as the
    renderer clamps them, :func:`.render.projection.project`); lp: the render's ``low_pass`` plus the 0.32 px^2
    that the radius formula's clamp can add."""
    fx, fy, cx, cy, w, h = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lx = max((w - cx - 0.5) / fx, (cx + 0.5) / fx) + 0.3 * tan_x
    ly = max((h - cy - 0.5) / fy, (cy + 0.5) / fy) + 0.3 * tan_y
    jb2 = fx * fx * (1.0 + lx * lx) + fy * fy * (1.0 + ly * ly)
    return np.array([fx, fy, cx, cy, w, h, NEAR, jb2, float(low_pass) + 0.32], np.float64)


def view_matrix(T_world_cam) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) float64 of the world-to-camera transform of ``T_world_cam`` (numpy: host arithmetic, no
    tensor), the same numbers as :func:`.projection.world_to_cam`."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    R = T[:3, :3].T
    return R, -R @ T[:3, 3]


def in_view(means: torch.Tensor, log_scales: torch.Tensor, camera: Camera, T_world_cam,
            low_pass: float = EPS2D) -> torch.Tensor:
    """Ids [M] int64 (ascending, on the map's device) of the Gaussians (raw means [N, 3], log scales [N, 3]) that
    can reach ``camera``'s image at ``T_world_cam``; a superset of those the renderer draws (with ``low_pass``).
    Compiled for float32 CPU rows, torch operators (:func:`in_view_torch`) otherwise."""
    if not compiled_rows(means, log_scales):
        return in_view_torch(means, log_scales, camera, T_world_cam, low_pass)
    from ..runtime.jit import rows_threads
    from ._cull_kernels import frustum_rows

    V = world_to_cam_np(T_world_cam)
    with rows_threads(means.shape[0], "frustum_rows"):
        rows = frustum_rows(means.detach().contiguous().numpy(), log_scales.detach().contiguous().numpy(), V,
                            camera_bounds(camera, low_pass))
    return torch.from_numpy(rows)


def in_view_torch(means: torch.Tensor, log_scales: torch.Tensor, camera: Camera, T_world_cam,
                  low_pass: float = EPS2D) -> torch.Tensor:
    """Ids [M] (ascending, on the map's device) of the rows that can reach the image: the bound of
    :func:`camera_bounds` in float64 torch operators."""
    cam = camera_bounds(camera, low_pass)
    R, t = view_matrix(T_world_cam)
    p = means.detach().double() @ torch.as_tensor(R.T, device=means.device) + torch.as_tensor(t, device=means.device)
    x, y, z = p.unbind(-1)
    front = z > cam[6]
    zs = torch.where(front, z, torch.ones_like(z))
    s = torch.exp(log_scales.detach().double().amax(-1).clamp(max=80.0))
    r = 3.0 * torch.sqrt(s * s * cam[7] / (zs * zs) + cam[8]) * 1.001 + 2.0
    u, v = cam[0] * x / zs + cam[2], cam[1] * y / zs + cam[3]
    hit = front & (u + r > -0.5) & (u - r < cam[4] - 0.5) & (v + r > -0.5) & (v - r < cam[5] - 0.5)
    return torch.nonzero(hit).squeeze(1)


def compiled_rows(*tensors: torch.Tensor) -> bool:
    """Whether the compiled row kernels take these tensors: float32 on the CPU."""
    return all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)


def map_in_view(gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> torch.Tensor:
    """:func:`in_view` of a map's rows; a float32 CPU map of :data:`.cell_index.MIN_ROWS` rows or more keeps a
    spatial index (:class:`.cell_index.CellIndex`) for it, which returns the same ids."""
    from .cell_index import MIN_ROWS, CellIndex

    means, log_scales = gmap.params["means"], gmap.params["scales"]
    if len(gmap) < MIN_ROWS or not compiled_rows(means, log_scales):
        gmap.row_index = None
        return in_view(means, log_scales, camera, T_world_cam, low_pass)
    if gmap.row_index is None:
        gmap.row_index = CellIndex(gmap)
    V = world_to_cam_np(T_world_cam)
    return torch.from_numpy(gmap.row_index.rows(V, camera_bounds(camera, low_pass)))


def gather_rows(gmap, idx: torch.Tensor, grad: bool) -> dict:
    """The rows ``idx`` of every raw parameter as new tensors (float32 contiguous CPU parameters: one compiled pass
    for all of them; otherwise torch's indexing)."""
    params = [gmap.params[n].detach() for n in PARAM_NAMES]
    if idx.device.type != "cpu" or any(p.dtype != torch.float32 or not p.is_contiguous() for p in params):
        return {n: p[idx].requires_grad_(grad) for n, p in zip(PARAM_NAMES, params)}
    from ..runtime.jit import rows_threads
    from ._cull_kernels import _gather_view

    outs = [torch.empty((idx.numel(),) + tuple(p.shape[1:]), dtype=torch.float32) for p in params]
    widths = [p[0].numel() if len(p) else 0 for p in params]  # shN of degree 0: width 0
    with rows_threads(idx.numel(), "gather_view"):
        _gather_view(tuple(p.view(len(p), w).numpy() for p, w in zip(params, widths)), idx.numpy(),
                     tuple(o.view(idx.numel(), w).numpy() for o, w in zip(outs, widths)))
    return {n: o.requires_grad_(grad) for n, o in zip(PARAM_NAMES, outs)}
