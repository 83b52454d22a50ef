"""Gaussian PLY in the standard 3DGS layout (what the reference viewers, SuperSplat and gsplat's tools read).

Vertex properties: x y z nx ny nz f_dc_0..2 f_rest_0..(3K-1) opacity scale_0..2 rot_0..3 - logit opacity, log
scale, wxyz quaternion, f_rest stored channel-major (all R coefficients, then G, then B) as 3DGS writes them.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .atomic import atomic_write
from ..core.gaussians import GaussianMap


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
    comments = [f"sh_degree {gmap.sh_degree}"]
    if gmap.supervision_focal is not None:  # the resolution it was fitted at: GaussianMap.low_pass
        comments.append(f"supervision_focal_px {gmap.supervision_focal!r}")
    ply = PlyData([PlyElement.describe(arr, "vertex")], comments=comments)
    return atomic_write(path, ply.write)  # a crash or full disk mid-write leaves the previous file intact


def load_ply(path: str | Path, device: str | torch.device = "cpu", lrs=None, adam=None) -> GaussianMap:
    """Read a 3DGS PLY into a fresh GaussianMap (SH degree inferred from the number of f_rest fields)."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        import stat

        try:
            mode = path.stat().st_mode
        except OSError:
            raise PlyError(f"{path}: no such file") from None
        kind = "a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else \
            "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file"
        raise PlyError(f"{path}: {kind}, not a PLY file")
    _check_vertex_count(path)
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
    gmap = GaussianMap(sh_degree=degree, device=device, lrs=lrs, adam=adam)
    k = n_rest // 3
    rest = col(*[f"f_rest_{i}" for i in range(n_rest)]) if n_rest else torch.zeros(n, 0)
    state = {
        "sh_degree": degree,
        "supervision_focal": _supervision_focal(path, ply.comments),
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


def _supervision_focal(path: Path, comments: list[str]) -> float | None:
    """The ``supervision_focal_px F`` header comment save_ply writes (None: absent, a PLY from elsewhere)."""
    for c in comments:
        key, _, value = c.partition(" ")
        if key == "supervision_focal_px":
            try:
                f = float(value)
            except ValueError:
                f = float("nan")
            if not (math.isfinite(f) and f > 0):
                raise PlyError(f"{path}: header comment 'supervision_focal_px' must be a positive number, "
                               f"got {value!r}")
            return f
    return None


_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
          "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_vertex_count(path: Path) -> None:
    """Raise PlyError when the vertex count in the header does not match the data after it (a truncated file, or
    a header edited by hand). Checked for files with one element of scalar properties (a Gaussian PLY); anything
    else is left to the PLY reader."""
    with open(path, "rb") as f:
        head = f.read(65536)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return  # not a PLY (the reader says so)
        start = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
        lines = head[:start].decode("ascii", "replace").splitlines()
        f.seek(0, 2)
        data = f.tell() - start
        body = None
        fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ") and len(ln.split()) > 1), "")
        if fmt == "ascii":
            f.seek(start)
            body = f.read()
    elements = [ln.split() for ln in lines if ln.startswith("element ")]
    props = [ln.split() for ln in lines if ln.startswith("property ")]
    if len(elements) != 1 or len(elements[0]) != 3 or any(len(p) != 3 or p[1] not in _SIZES for p in props):
        return
    try:
        n = int(elements[0][2])
    except ValueError:
        raise PlyError(f"{path}: element {elements[0][1]!r} has no valid count ({elements[0][2]!r})") from None
    name = elements[0][1]
    if body is not None:
        rows = sum(1 for ln in body.splitlines() if ln.strip())
        if rows != n:
            raise PlyError(f"{path}: wrong {name} count: the header declares {n} but the file holds {rows} rows"
                           f"{' (truncated?)' if rows < n else ''}")
        return
    row = sum(_SIZES[p[1]] for p in props)
    if row and data != n * row:
        raise PlyError(f"{path}: wrong {name} count: the header declares {n} ({n * row} bytes) but the file holds "
                       f"{data} bytes of data, {data // row} whole {name} rows"
                       f"{' (truncated?)' if data < n * row else ''}")
