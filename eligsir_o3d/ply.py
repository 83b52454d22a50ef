"""Gaussian PLY in the standard 3DGS layout (what the reference viewers, SuperSplat and gsplat's tools read).

Vertex properties: x y z nx ny nz f_dc_0..2 f_rest_0..(3K-1) opacity scale_0..2 rot_0..3 - logit opacity, log
scale, wxyz quaternion, f_rest stored channel-major (all R coefficients, then G, then B) as 3DGS writes them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .atomic_io import atomic_write
from .gaussians import GaussianMap


class PlyError(ValueError):
    """A PLY file that is not a readable 3DGS Gaussian map (names the file and the missing fields)."""


def save_ply(gmap: GaussianMap, path: str | Path) -> Path:
    from plyfile import PlyData, PlyElement

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    p = {k: v.detach().cpu().numpy() for k, v in gmap.params.items()}
    n = p["means"].shape[0]
    k = p["shN"].shape[1]
    rest = p["shN"].transpose(0, 2, 1).reshape(n, 3 * k)  # channel-major, as 3DGS
    cols = [("x", p["means"][:, 0]), ("y", p["means"][:, 1]), ("z", p["means"][:, 2]),
            ("nx", np.zeros(n)), ("ny", np.zeros(n)), ("nz", np.zeros(n))]
    cols += [(f"f_dc_{i}", p["sh0"][:, 0, i]) for i in range(3)]
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(3 * k)]
    cols += [("opacity", p["opacities"])]
    cols += [(f"scale_{i}", p["scales"][:, i]) for i in range(3)]
    cols += [(f"rot_{i}", p["quats"][:, i]) for i in range(4)]
    arr = np.empty(n, dtype=[(name, "f4") for name, _ in cols])
    for name, v in cols:
        arr[name] = v
    ply = PlyData([PlyElement.describe(arr, "vertex")], comments=[f"sh_degree {gmap.sh_degree}"])
    return atomic_write(path, ply.write)  # a crash or full disk mid-write leaves the previous file intact


def load_ply(path: str | Path, device: str | torch.device = "cpu", lrs=None) -> GaussianMap:
    """Read a 3DGS PLY into a fresh GaussianMap (SH degree inferred from the number of f_rest fields)."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise PlyError(f"{path}: no such file")
    try:
        ply = PlyData.read(str(path), mmap=False)
        v = ply["vertex"]
    except Exception as e:  # plyfile raises several types on malformed input
        raise PlyError(f"{path}: not a readable PLY with a 'vertex' element ({e})") from None
    names = set(v.data.dtype.names)
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [f for f in need if f not in names]
    if missing:
        raise PlyError(f"{path}: not a 3DGS Gaussian PLY, missing vertex properties {missing}")
    n_rest = len([f for f in names if f.startswith("f_rest_")])
    degree = {0: 0, 9: 1, 24: 2, 45: 3}.get(n_rest)
    if degree is None:
        raise PlyError(f"{path}: {n_rest} f_rest_* properties do not match any SH degree (expected 0, 9, 24 or 45)")

    def col(*fields):
        return torch.from_numpy(np.stack([np.asarray(v[f], dtype=np.float32) for f in fields], -1))

    n = len(v.data)
    gmap = GaussianMap(sh_degree=degree, device=device, lrs=lrs)
    k = n_rest // 3
    rest = col(*[f"f_rest_{i}" for i in range(n_rest)]) if n_rest else torch.zeros(n, 0)
    state = {
        "sh_degree": degree,
        "params": {
            "means": col("x", "y", "z"),
            "scales": col("scale_0", "scale_1", "scale_2"),
            "quats": col("rot_0", "rot_1", "rot_2", "rot_3"),
            "opacities": col("opacity")[:, 0],
            "sh0": col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
            "shN": rest.reshape(n, 3, k).transpose(1, 2).contiguous(),
        },
    }
    for name, t in state["params"].items():
        if not torch.isfinite(t).all():
            raise PlyError(f"{path}: property group '{name}' contains NaN or Inf")
    gmap.load_state_dict(state)
    return gmap
