"""Colour-camera intrinsics measured from the recording itself: photometric consistency of depth-warped colour.

Where a recording's colour camera is not calibrated (7-Scenes gives one intrinsic for both of its cameras),
the colour intrinsics can still be measured, because only the right ones make the colours agree across views:
each depth pixel of frame i is back-projected with the depth intrinsics and moved by the poses into frame j; a
candidate colour camera K projects that surface point into both colour images, and the colour found there must
be the same when K is right (a wrong focal length or principal point samples neighbouring surface points, which
rotation and parallax between the views move differently). The error of a candidate is the mean absolute colour
difference over all frame pairs; the estimate minimises it, first over the focal length (fx, fy scaled
together from the depth camera's), then over the principal point, which is kept at the depth camera's unless its
error curve has a clear interior minimum, then over the focal length again. Surface points occluded in frame j
(seen by its depth at another distance) are left out, so the check needs only the depth camera's geometry.

The cameras are treated as co-located unless the sequence's rig gives a depth-to-colour extrinsic.
``eligsir calibrate-color PATH`` prints the error curves and, with ``--write``, stores the estimate as the
``color`` block of the folder's ``intrinsics.json`` (see :mod:`.datasets.registration`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.camera import Camera, invert_pose


@dataclass
class _Pair:
    i: int
    j: int
    points_i: np.ndarray  # [M, 3] surface points in colour camera i's frame (metres)
    points_j: np.ndarray  # [M, 3] the same points in colour camera j's frame
    color_i: np.ndarray  # [H, W, 3] float32 in [0, 1], downsampled by the search's factor
    color_j: np.ndarray


@dataclass
class ColorCalibration:
    """The estimate and the evidence: error curves (value, mean absolute colour difference) of each search."""

    camera: Camera  # estimated colour camera, at the colour images' size
    start: Camera  # the depth camera's intrinsics at the colour images' size (the search's starting point)
    error: float  # mean absolute colour difference of the estimate
    error_start: float
    f_curve: list[tuple[float, float]] = field(default_factory=list)  # (fx, error) of the coarse search
    f_fine: list[tuple[float, float]] = field(default_factory=list)  # (fx, error) after the principal point
    cx_curve: list[tuple[float, float]] = field(default_factory=list)
    cy_curve: list[tuple[float, float]] = field(default_factory=list)
    principal_point: bool = False  # True when cx, cy were identified (else the depth camera's are kept)
    pairs: list[tuple[int, int]] = field(default_factory=list)
    points: int = 0  # surface points compared per candidate (all pairs)
    checks: dict[str, float] = field(default_factory=dict)  # name -> error of other cameras (e.g. the sidecar's)

    def report(self) -> str:
        c, s = self.camera, self.start
        lines = [f"frame pairs: {', '.join(f'{i}-{j}' for i, j in self.pairs)} ({self.points} surface points)",
                 "focal length (fx; fy scales with it)   mean |colour difference|"]
        lines += _curve_lines(self.f_curve, c.fx)
        if self.cx_curve:
            lines.append(f"principal point ({'identified' if self.principal_point else 'not identifiable: kept'})")
            lines += ["  cx"] + _curve_lines(self.cx_curve, c.cx) + ["  cy"] + _curve_lines(self.cy_curve, c.cy)
        if self.f_fine:
            lines.append("focal length, refined")
            lines += _curve_lines(self.f_fine, c.fx)
        lines.append(f"depth camera's intrinsics: fx={s.fx:.1f} fy={s.fy:.1f} cx={s.cx:.1f} cy={s.cy:.1f}  "
                     f"error {self.error_start:.4f}")
        for name, err in self.checks.items():
            lines.append(f"{name}: error {err:.4f}")
        lines.append(f"estimate: fx={c.fx:.1f} fy={c.fy:.1f} cx={c.cx:.1f} cy={c.cy:.1f}  error {self.error:.4f}  "
                     f"({(c.fx / s.fx - 1) * 100:+.1f} % focal length vs the depth camera)")
        return "\n".join(lines)


def _curve_lines(curve: list[tuple[float, float]], best: float) -> list[str]:
    if not curve:
        return []
    errs = np.array([e for _, e in curve])
    finite = errs[np.isfinite(errs)]
    lo, hi = (finite.min(), finite.max()) if finite.size else (0.0, 1.0)
    k = int(np.argmin(np.abs(np.array([v for v, _ in curve]) - best)))
    out = []
    for n, (v, e) in enumerate(curve):
        bar = "#" * int(round(30 * (e - lo) / (hi - lo))) if np.isfinite(e) and hi > lo else ""
        out.append(f"  {v:8.1f}  {e:.4f}  {bar}{'  <' if n == k else ''}")
    return out


# -- the measurement -----------------------------------------------------------------------------------------
def _downsample(color: np.ndarray, k: int) -> np.ndarray:
    """uint8 [H, W, 3] -> float32 [H // k, W // k, 3] in [0, 1], area average."""
    c = color.astype(np.float32) / 255.0
    if k == 1:
        return c
    h, w = (c.shape[0] // k) * k, (c.shape[1] // k) * k
    return c[:h, :w].reshape(h // k, k, w // k, k, 3).mean(axis=(1, 3))


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples [M, 3] of image [H, W, 3] at pixel coordinates (centres at integers), all in bounds."""
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    a, b = (u - u0)[:, None], (v - v0)[:, None]
    return ((image[v0, u0] * (1 - a) + image[v0, u0 + 1] * a) * (1 - b)
            + (image[v0 + 1, u0] * (1 - a) + image[v0 + 1, u0 + 1] * a) * b)


def _project(points: np.ndarray, K: tuple[float, float, float, float], w: int, h: int):
    fx, fy, cx, cy = K
    z = points[:, 2]
    u = fx * points[:, 0] / z + cx
    v = fy * points[:, 1] / z + cy
    return u, v, (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)


def pair_error(pairs: list[_Pair], camera: Camera, k: int) -> float:
    """Mean absolute colour difference of all pairs' surface points under colour camera ``camera``."""
    fx, fy = camera.fx / k, camera.fy / k
    cx, cy = (camera.cx + 0.5) / k - 0.5, (camera.cy + 0.5) / k - 0.5
    total, count = 0.0, 0
    for p in pairs:
        h, w = p.color_i.shape[:2]
        ui, vi, oki = _project(p.points_i, (fx, fy, cx, cy), w, h)
        uj, vj, okj = _project(p.points_j, (fx, fy, cx, cy), w, h)
        ok = oki & okj
        if not ok.any():
            continue
        diff = _sample(p.color_i, ui[ok], vi[ok]) - _sample(p.color_j, uj[ok], vj[ok])
        total += float(np.abs(diff).sum())
        count += diff.size
    return total / count if count else float("inf")


def _prepare(seq, pairs: list[tuple[int, int]], stride: int, k: int, depth_max: float) -> list[_Pair]:
    dcam = seq.depth_camera
    T_cd = seq.rig.T_color_depth if seq.rig is not None else np.eye(4)
    raw: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def images(i: int):
        if i not in raw:
            color, depth = seq.raw_images(i)
            raw[i] = (_downsample(color, k), depth.astype(np.float32) / seq.depth_scale)
        return raw[i]

    out = []
    for i, j in pairs:
        (ci, di), (cj, dj) = images(i), images(j)
        v, u = np.mgrid[0:dcam.height:stride, 0:dcam.width:stride]
        z = di[v, u]
        ok = (z > 0) & (z < depth_max)
        u, v, z = u[ok], v[ok], z[ok]
        X_di = dcam.unproject(u, v, z)
        # depth-camera poses (the sequence's are the colour camera's when it has a rig): T_wd = T_wc @ T_cd
        T_ji = invert_pose(seq.poses[j] @ T_cd) @ (seq.poses[i] @ T_cd)
        X_dj = X_di @ T_ji[:3, :3].T + T_ji[:3, 3]
        # visible in frame j: its depth camera measures this point at about the same distance
        zj = X_dj[:, 2]
        front = zj > 0.05
        uj = np.rint(dcam.fx * X_dj[:, 0] / np.where(front, zj, 1) + dcam.cx).astype(np.int64)
        vj = np.rint(dcam.fy * X_dj[:, 1] / np.where(front, zj, 1) + dcam.cy).astype(np.int64)
        inside = front & (uj >= 0) & (uj < dcam.width) & (vj >= 0) & (vj < dcam.height)
        seen = np.zeros_like(inside)
        d_obs = dj[vj[inside], uj[inside]]
        seen[inside] = (d_obs > 0) & (np.abs(d_obs - zj[inside]) < 0.02 + 0.03 * zj[inside])
        if seen.sum() < 50:
            continue
        to_c = lambda X: X[seen] @ T_cd[:3, :3].T + T_cd[:3, 3]  # noqa: E731
        out.append(_Pair(i, j, to_c(X_di), to_c(X_dj), ci, cj))
    return out


def choose_pairs(poses: list[np.ndarray], count: int, gap: int | None = None, min_angle_deg: float = 6.0,
                 min_move_m: float = 0.12) -> list[tuple[int, int]]:
    """``count`` frame pairs (i, j) with i spread evenly over the poses.

    j is i + gap when ``gap`` is given, else the first later frame that has turned by ``min_angle_deg`` or moved
    by ``min_move_m`` (enough motion that a wrong colour camera shows, little enough that pose errors and the
    shrinking overlap do not dominate: about 6 degrees is 20 frames of 7-Scenes, 10 of SUN3D).
    """
    n = len(poses)
    if n < 2:
        raise ValueError(f"colour calibration needs at least 2 frames, the sequence has {n}")
    if gap is not None:
        gap = max(1, min(int(gap), n - 1))
        starts = np.unique(np.linspace(0, n - 1 - gap, max(1, count)).round().astype(int))
        return [(int(i), int(i) + gap) for i in starts]
    partner = []
    for i in range(n):
        j = next((j for j in range(i + 1, n) if _moved(poses[i], poses[j], min_angle_deg, min_move_m)), None)
        if j is None:
            break  # later starts cannot find a partner either (fewer frames left)
        partner.append(j)
    if not partner:  # the camera hardly moves: take the two ends
        return [(0, n - 1)]
    starts = np.unique(np.linspace(0, len(partner) - 1, max(1, count)).round().astype(int))
    return [(int(i), partner[i]) for i in starts]


def _moved(T_a: np.ndarray, T_b: np.ndarray, min_angle_deg: float, min_move_m: float) -> bool:
    T = invert_pose(T_b) @ T_a
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return bool(angle >= min_angle_deg or np.linalg.norm(T[:3, 3]) >= min_move_m)


def _grid_min(fn, values: np.ndarray) -> tuple[float, list[tuple[float, float]]]:
    """Arg-min of fn over values, refined by a parabola through the best point and its neighbours."""
    curve = [(float(x), fn(float(x))) for x in values]
    errs = np.array([e for _, e in curve])
    b = int(np.argmin(errs))
    best = float(values[b])
    if 0 < b < len(values) - 1 and np.all(np.isfinite(errs[b - 1:b + 2])):
        e0, e1, e2 = errs[b - 1:b + 2]
        den = e0 - 2 * e1 + e2
        if den > 0:
            best += 0.5 * (e0 - e2) / den * float(values[b + 1] - values[b])
    return best, curve


def calibrate_color(seq, *, pairs: int = 8, gap: int | None = None, stride: int = 4, downsample: int = 2,
                    f_range: tuple[float, float] = (0.75, 1.25), f_steps: int = 51,
                    principal_point: bool = True, pp_range: float = 0.06, pp_steps: int = 13,
                    pp_min_gain: float = 0.01, depth_max: float = 8.0, frames: int | None = None) -> ColorCalibration:
    """Estimate the colour camera of ``seq`` (an RGBDSequence with poses) by photometric consistency.

    pairs, gap: how many frame pairs are compared, spread over the first ``frames`` frames (all by default);
    each pairs a frame with the first that has turned by 6 degrees or moved by 12 cm (or with i + gap).
    stride: every stride-th depth pixel in x and y is a surface point; downsample: colour is area-averaged by this
    integer factor (smoother error curves, faster). f_range, f_steps: the focal-length search, as factors of the
    depth camera's. pp_range, pp_steps: the principal-point search, +- this fraction of the image size;
    the principal point counts as identified only when it lowers the error by more than ``pp_min_gain``
    (relative) at an interior minimum.
    """
    for name, v in (("--pairs", pairs), ("--stride", stride), ("downsample", downsample)):
        if not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be a whole number >= 1, got {v}")
    if gap is not None and gap < 1:
        raise ValueError(f"--gap must be a whole number >= 1, got {gap}")
    if frames is not None and frames < 2:
        raise ValueError(f"--max-frames must be at least 2 for colour calibration (frame pairs), got {frames}")
    if seq.poses is None:
        raise ValueError(f"{seq.path or seq.name}: colour calibration needs poses (the sequence has none)")
    n = len(seq) if frames is None else min(len(seq), int(frames))
    chosen = choose_pairs(seq.poses[:n], pairs, gap)
    both = chosen + [(j, i) for i, j in chosen]  # both directions: each view is once the source, once the target
    prepared = _prepare(seq, both, stride, downsample, depth_max)
    if not prepared:
        raise ValueError(f"{seq.path or seq.name}: no frame pair of {chosen} sees enough common surface; "
                         f"try a smaller --gap")
    d = seq.depth_camera
    cw, ch = seq.camera.width, seq.camera.height  # the colour images' size
    sx, sy = cw / d.width, ch / d.height
    start = Camera(cw, ch, d.fx * sx, d.fy * sy, (d.cx + 0.5) * sx - 0.5, (d.cy + 0.5) * sy - 0.5)
    ratio = start.fy / start.fx

    def cam(fx: float, cx: float, cy: float) -> Camera:
        return Camera(cw, ch, fx, fx * ratio, cx, cy)

    err = lambda c: pair_error(prepared, c, downsample)  # noqa: E731
    fx, f_curve = _grid_min(lambda f: err(cam(f, start.cx, start.cy)), start.fx * np.linspace(*f_range, f_steps))
    cx, cy, pp_ok, cx_curve, cy_curve, f_fine = start.cx, start.cy, False, [], [], []
    if principal_point:
        base = err(cam(fx, cx, cy))
        offsets = np.linspace(-pp_range, pp_range, pp_steps)
        cx_new, cx_curve = _grid_min(lambda c: err(cam(fx, c, cy)), cx + cw * offsets)
        cy_new, cy_curve = _grid_min(lambda c: err(cam(fx, cx_new, c)), cy + ch * offsets)
        interior = all(min(c)[0] < v < max(c)[0] for c, v in ((cx_curve, cx_new), (cy_curve, cy_new)))
        gain = 1 - err(cam(fx, cx_new, cy_new)) / base
        if interior and gain > pp_min_gain:
            pp_ok, cx, cy = True, cx_new, cy_new
            fx, f_fine = _grid_min(lambda f: err(cam(f, cx, cy)), fx * np.linspace(0.95, 1.05, 21))
    result = ColorCalibration(camera=cam(fx, cx, cy), start=start, error=err(cam(fx, cx, cy)),
                              error_start=err(start), f_curve=f_curve, f_fine=f_fine, cx_curve=cx_curve,
                              cy_curve=cy_curve, principal_point=pp_ok, pairs=chosen,
                              points=sum(len(p.points_i) for p in prepared))
    if seq.rig is not None:
        c = seq.rig.color
        result.checks[f"current colour camera (fx={c.fx:.1f} cx={c.cx:.1f} cy={c.cy:.1f})"] = err(c)
    return result


def write_estimate(seq, result: ColorCalibration):
    """Store ``result.camera`` as the ``color`` block of the sequence folder's ``intrinsics.json``.

    A folder without a sidecar gets one: the depth camera's intrinsics and depth scale at the top level (what the
    reader used), the estimate in the ``color`` block. Returns the sidecar's path.
    """
    import json

    from .registration import write_color_block

    if seq.path is None:
        raise ValueError(f"sequence {seq.name!r} has no folder to write an intrinsics.json into")
    sidecar = seq.path / "intrinsics.json"
    if not sidecar.is_file():
        d = seq.depth_camera
        sidecar.write_text(json.dumps({"width": d.width, "height": d.height, "fx": d.fx, "fy": d.fy, "cx": d.cx,
                                       "cy": d.cy, "depth_scale": seq.depth_scale}, indent=2) + "\n")
    c = result.camera
    note = (f"estimated by eligsir calibrate-color: photometric consistency of depth-warped colour over "
            f"{len(result.pairs)} frame pairs, error {result.error:.4f} (depth camera's intrinsics: "
            f"{result.error_start:.4f}); principal point "
            f"{'estimated' if result.principal_point else 'not identifiable, kept at the depth camera'}")
    write_color_block(sidecar, c, note, None if seq.rig is None else seq.rig.T_color_depth)
    return sidecar
