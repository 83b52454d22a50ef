"""Inputs shared by the device-step tests: a map with rows in and out of a view, the view's host scalars, and a
render's accumulations with a reference image."""

from __future__ import annotations

import numpy as np
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.render.culling import camera_bounds
from eligsir_o3d.render.projection import world_to_cam

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def make_map(n=400, seed=0, sh_degree=0, spread=2.0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * spread
    means[:, 2] += 2.0
    gm = GaussianMap(sh_degree)
    gm.add(means, torch.rand(n, 3, generator=g), torch.rand(n, generator=g) * 0.2 + 0.01, 0.5,
           torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))
    with torch.no_grad():  # varied opacities, colours (some clamped at 0) and SH
        gm.params["opacities"].copy_(torch.randn(n, generator=g) * 3.0)
        gm.params["sh0"].copy_(torch.randn(n, 1, 3, generator=g) * 2.0)
        gm.params["shN"].copy_(torch.randn(gm.params["shN"].shape, generator=g) * 0.1)
    return gm


def pose(yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [0.1, -0.05, 0.0]
    return T


def view_scalars(T, camera=CAM):
    """(V: 12 host floats, cam: 9 host floats) of a camera-to-world pose."""
    V = world_to_cam(T, "cpu", torch.float64).numpy()
    return tuple(float(v) for v in V[:3].reshape(-1)), tuple(float(c) for c in camera_bounds(camera))


def accumulations(h, w, seed=0):
    """(acc [h, w, 4], alpha [h, w], colour [h, w, 3], depth [h, w]) with undrawn pixels, alpha below the depth
    floor and missing depth."""
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(h, w, generator=g)
    alpha[0, :5] = 0.0
    alpha[-1, :3] = 5e-5
    rgb = torch.rand(h, w, 3, generator=g) * alpha[..., None]
    dep = (1.0 + 2.0 * torch.rand(h, w, generator=g)) * alpha
    ref = torch.rand(h, w, 3, generator=g)
    ref_depth = 1.0 + 2.0 * torch.rand(h, w, generator=g)
    ref_depth[::3, ::4] = 0.0
    return torch.cat([rgb, dep[..., None]], -1), alpha, ref, ref_depth
