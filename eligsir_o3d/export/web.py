"""Maps for the web: SPZ (Niantic's compressed splats) and ``.splat`` (antimatter15's 32-byte records).

    write_web(rec.gmap, spz="map.spz", splat="map.splat", camera=rec.camera, poses=poses)   # `eligsir export --spz`

The map goes from memory into Open3D's Gaussian-splat point cloud (:func:`splat_cloud`: the fields its 3DGS PLY
reader makes), with the low-pass of the resolution it was supervised at baked in for players that add 3DGS's fixed
0.3 px^2 (:func:`.viewers.for_viewers`; nothing is baked without a camera and poses). Both formats are written by
Open3D 0.20 (``o3d.t.io.write_point_cloud``), which writes what it is given. The formats' axis conventions
differ, so this module converts first:

- SPZ stores RUB (x right, y up, z back: OpenGL / three.js), and its readers (the spz library, SuperSplat,
  Spark, Scaniverse) convert from RUB to their own axes. Our maps are RDF (x right, y down, z forward: OpenCV, the
  3DGS PLY convention), so the map is turned by 180 degrees about x before writing: positions (x, -y, -z),
  quaternions (w, x, -y, -z), and the view-dependent colour's SH coefficients of degree >= 1 get the signs of
  their basis functions under y -> -y, z -> -z. This is what the spz library's ``PackOptions{from = RDF}`` does,
  and what ``splat-transform`` undoes when it reads the SPZ back into a PLY (the test compares the two).
- ``.splat`` has no axis field; its writers (antimatter15's converter, splat-transform) copy 3DGS PLY axes, and
  its viewers expect them: written as they are.

SPZ quantises: positions to 12 fractional bits (1/4096 m, the spz library's fixed choice), log-scales to 1/16,
opacity and colour to 8 bits, rotations to ~10 bits per component (smallest three), and compresses each attribute
stream with ZSTD (SPZ v4). ZSTD codes these streams almost byte by byte: reordering by position (Morton) gains
nothing (under 0.3 %), but writing the Gaussians in order of their 8-bit opacity turns that stream into runs
(0.96 -> 0.11 bytes a Gaussian) at no cost to the others; the order of splats means nothing to a renderer, which
sorts them by depth. At SH degree 0 the PLY spends 68 bytes a Gaussian and SPZ ~15.8 (positions 6.8, rotation 3.75,
colour 2.75, scales 2.3, opacity 0.1): 4.3x. The four non-position streams alone are 9 bytes a Gaussian, so 6x
(11.3 bytes) is out of reach at degree 0 without coarser positions than the format's readers assume; with SH
degree 3 (the PLY at 248 bytes a Gaussian) SPZ is well over 6x smaller.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import open3d as o3d

from ..core.camera import Camera
from ..core.gaussians import GaussianMap

# sign of each real SH basis function (degrees 1..3, in the 3DGS order) under (x, y, z) -> (x, -y, -z)
SH_SIGNS_RDF_RUB = np.array([-1, -1, 1,  # y, z, x
                             -1, 1, 1, -1, 1,  # xy, yz, 3z^2 - r^2, xz, x^2 - y^2
                             -1, 1, -1, -1, 1, -1, 1], dtype=np.float32)  # degree 3
WEB_FORMATS = ("ply", "spz", "splat")
SPZ_REACH_M = 2.0 ** 23 / 2.0 ** 12  # 2048 m: signed 24-bit positions at the 12 fractional bits Open3D writes


def parse_formats(text: str) -> list[str]:
    """``"ply,spz"`` -> ["ply", "spz"]; ValueError naming an unknown one. PLY is always written."""
    names = [t.strip().lower() for t in str(text).split(",") if t.strip()]
    bad = [t for t in names if t not in WEB_FORMATS]
    if bad:
        raise ValueError(f"unknown map format(s) {', '.join(bad)}; choose from {', '.join(WEB_FORMATS)}")
    return ["ply"] + [t for t in dict.fromkeys(names) if t != "ply"]


def splat_cloud(gmap: GaussianMap) -> o3d.t.geometry.PointCloud:
    """``gmap`` as Open3D's Gaussian-splat point cloud, field for field what Open3D's reader makes of the map's
    3DGS PLY: positions [N, 3], f_dc [N, 3], f_rest [N, K, 3] (SH degree >= 1), opacity [N, 1] (logit), rot
    [N, 4] (wxyz, as stored) and scale [N, 3] in metres (the log-scales through float32 ``expf``, as the reader
    activates them)."""
    p = {k: np.ascontiguousarray(v.detach().cpu().float().numpy()) for k, v in gmap.params.items()}
    fields = {"positions": p["means"], "f_dc": p["sh0"][:, 0], "opacity": p["opacities"][:, None],
              "scale": _expf()(p["scales"]), "rot": p["quats"]}
    if p["shN"].shape[1]:
        fields["f_rest"] = p["shN"]
    cloud = o3d.t.geometry.PointCloud()
    for key, a in fields.items():
        cloud.point[key] = o3d.core.Tensor(np.ascontiguousarray(a, np.float32))
    return cloud


def _exp32(x):
    return math.exp(x)


@functools.lru_cache(maxsize=1)
def _expf():
    """A float32 ``exp`` ufunc by the C library's ``expf``, the one Open3D's PLY reader calls (numpy's and torch's
    float32 ``exp`` differ from it in the last bit for some inputs)."""
    from ..runtime import jit  # numba, with the process's threading layer chosen

    return jit.numba.vectorize(["float32(float32)"], cache=True)(_exp32)


def rdf_to_rub(pcd: o3d.t.geometry.PointCloud) -> o3d.t.geometry.PointCloud:
    """A copy of a splat cloud turned from RDF to RUB axes (180 degrees about x; see the module docstring)."""
    out = o3d.t.geometry.PointCloud()
    for key in ("positions", "f_dc", "opacity", "scale", "rot", "f_rest"):
        if key not in pcd.point:
            continue
        a = pcd.point[key].numpy().astype(np.float32).copy()
        if key == "positions":
            a[:, 1:] *= -1.0
        elif key == "rot":  # wxyz
            a[:, 2:] *= -1.0
        elif key == "f_rest":  # Open3D holds [N, K, 3]: K coefficients (degree 1 first), RGB innermost
            a = a * SH_SIGNS_RDF_RUB[:a.shape[1], None]
        out.point[key] = o3d.core.Tensor(a)
    return out


def spz_order(pcd: o3d.t.geometry.PointCloud) -> np.ndarray:
    """Permutation [N] (int64) putting the Gaussians in order of the 8-bit opacity SPZ stores (a stable sort):
    that stream then compresses to runs. Applied to the cloud before it is written as SPZ."""
    logit = pcd.point["opacity"].numpy().reshape(-1).astype(np.float64)
    alpha_byte = np.clip(np.round(255.0 * 0.5 * (1.0 + np.tanh(0.5 * logit))), 0, 255)  # sigmoid, overflow-free
    return np.argsort(alpha_byte, kind="stable")


def _reordered(pcd: o3d.t.geometry.PointCloud, order: np.ndarray) -> o3d.t.geometry.PointCloud:
    out = o3d.t.geometry.PointCloud()
    for key in ("positions", "f_dc", "opacity", "scale", "rot", "f_rest"):
        if key in pcd.point:
            out.point[key] = o3d.core.Tensor(np.ascontiguousarray(pcd.point[key].numpy()[order]))
    return out


def check_web_path(path: str | Path, fmt: str) -> None:
    """Refuse (ValueError) an output path for format ``fmt`` ("spz" or "splat") that ends in another map
    format's suffix: the file would be read as the wrong format."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix in WEB_FORMATS and suffix != fmt:
        raise ValueError(f"--{fmt} {path}: the name ends in .{suffix} but the file would be {fmt.upper()}; give a "
                         f".{fmt} path (or use --{suffix})")


def _write(path: Path, pcd, fmt: str) -> Path:
    """Write ``pcd`` as ``fmt`` (the format, whatever ``path``'s suffix) through :func:`.io.atomic.temp_for` and
    :func:`.io.atomic.commit_file`: a reader never sees half a file, a device is never replaced."""
    from ..io.atomic import WriteFailed, commit_file, temp_for, write_failed

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_for(path, f".{fmt}")
    except OSError as e:
        raise write_failed(path, e) from None
    try:
        if not o3d.t.io.write_point_cloud(str(tmp), pcd):
            raise WriteFailed(path, f"Open3D could not write the {fmt.upper()} file (folder not writable or "
                              f"disk full?)")
        return commit_file(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _size(path: Path) -> int | None:
    """Bytes of a written file (None for a device or FIFO it was written into)."""
    return path.stat().st_size if path.is_file() else None


def write_web(gmap: GaussianMap, spz: str | Path | None = None, splat: str | Path | None = None,
              camera: Camera | None = None, poses: Sequence[np.ndarray] | None = None) -> dict:
    """Write ``gmap`` as SPZ (Gaussians in :func:`spz_order`) and/or ``.splat`` (in the map's order), its
    low-pass baked in for ``camera`` at ``poses`` (camera-to-world; :func:`.viewers.for_viewers`). Returns
    {"gaussians", "spz_bytes", "splat_bytes", "baked_low_pass_px2"} (0.3: nothing baked)."""
    from .viewers import for_viewers

    if spz is None and splat is None:
        raise ValueError("nothing to write: give an .spz and/or a .splat path")
    for target, fmt in ((spz, "spz"), (splat, "splat")):
        if target is not None:
            check_web_path(target, fmt)
    shown, low_pass = for_viewers(gmap, camera, poses)
    cloud = splat_cloud(shown)
    summary = {"gaussians": len(shown)}
    if spz is not None:
        reach = float(np.abs(cloud.point.positions.numpy()).max(initial=0.0))
        if not reach < SPZ_REACH_M:  # 24-bit fixed point with 12 fractional bits: larger values would wrap around
            raise ValueError(f"{spz}: a Gaussian lies {reach:.0f} m from the origin; SPZ positions reach "
                             f"{SPZ_REACH_M:.0f} m (recentre the map before exporting)")
        rub = rdf_to_rub(cloud)
        summary["spz_bytes"] = _size(_write(Path(spz), _reordered(rub, spz_order(rub)), "spz"))
    if splat is not None:
        summary["splat_bytes"] = _size(_write(Path(splat), cloud, "splat"))
    summary["baked_low_pass_px2"] = low_pass
    return summary
