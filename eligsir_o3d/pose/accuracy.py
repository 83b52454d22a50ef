"""Trajectory accuracy: ATE RMSE after a Umeyama alignment, relative pose error, and a top-view plot.

Both trajectories are camera-to-world poses keyed by timestamp. They are associated by nearest timestamp
(``max_diff`` seconds, as TUM's ``associate.py``), the estimate is aligned to the ground truth by the
least-squares rigid transform of the matched camera centres (Umeyama 1991; no scale for RGB-D, whose depth is
metric; ``with_scale=True`` for monocular estimates), and then:

- ``ate_rmse_m``: RMSE of the camera-centre distances after alignment (Sturm et al. 2012, TUM RGB-D);
- ``rpe_trans_m`` / ``rpe_rot_deg``: RMSE over consecutive matched pairs of the translational / rotational part of
  ``(Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (per frame-pair drift; alignment-free).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence, Union

import numpy as np

Trajectory = Union[Mapping[float, np.ndarray], tuple[Sequence[float], Sequence[np.ndarray]]]


def as_arrays(traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps [N] float64 sorted, poses [N, 4, 4] float64) of a dict or a (timestamps, poses) pair."""
    if isinstance(traj, Mapping):
        stamps, poses = list(traj.keys()), list(traj.values())
    else:
        stamps, poses = traj
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(np.stack([np.asarray(T, dtype=np.float64) for T in poses]) if len(poses) else
                       np.zeros((0, 4, 4)), dtype=np.float64)
    if poses.shape[1:] != (4, 4) or len(stamps) != len(poses):
        raise ValueError(f"trajectory: {len(stamps)} timestamps and poses of shape {poses.shape} (want [N, 4, 4])")
    order = np.argsort(stamps, kind="stable")
    return stamps[order], poses[order]


def associate_stamps(a: np.ndarray, b: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of one-to-one nearest-timestamp matches with |a - b| <= max_diff (closest pairs first)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    pos = np.clip(np.searchsorted(b, a), 1, max(len(b) - 1, 1)) if len(b) > 1 else np.zeros(len(a), np.int64)
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(b[left] - a) <= np.abs(b[pos] - a), left, pos)
    diff = np.abs(b[pick] - a)
    ia, ib, used = [], [], set()
    for i in np.argsort(diff, kind="stable"):
        j = int(pick[i])
        if diff[i] <= max_diff and j not in used:
            used.add(j)
            ia.append(int(i))
            ib.append(j)
    order = np.argsort(ia)
    return np.asarray(ia, dtype=np.int64)[order], np.asarray(ib, dtype=np.int64)[order]


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, float]:
    """Least-squares similarity (4x4 rigid part, scale) mapping points ``src`` [N, 3] onto ``dst`` [N, 3].

    Returns (T [4, 4] with rotation and translation, s): dst ~= s * R @ src + t. ``s`` is 1 unless
    ``with_scale``. Needs N >= 3 points that are not all collinear for a unique rotation.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama_alignment: point sets must both be [N, 3], got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama_alignment: need at least 3 point pairs, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_d - s * R @ mu_s
    return T, s


def pose_alignment(est: Sequence[np.ndarray], gt: Sequence[np.ndarray]) -> np.ndarray:
    """T_gt_est from whole poses (matched lists): rotation = SVD projection of sum_i R_gt,i R_est,i^T, then the
    mean translation.

    Unlike a positions-only (Umeyama) fit, this stays well conditioned on short, nearly straight trajectories,
    where many rotations explain the camera centres equally well but disagree on where the cameras look.
    """
    P = np.stack([np.asarray(T, dtype=np.float64) for T in est])
    Q = np.stack([np.asarray(T, dtype=np.float64) for T in gt])
    M = np.einsum("nij,nkj->ik", Q[:, :3, :3], P[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (Q[:, :3, 3] - P[:, :3, 3] @ R.T).mean(0)
    return T


def _angle_deg(R: np.ndarray) -> np.ndarray:  # R [..., 3, 3] -> [...]
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def trajectory_accuracy(est: Trajectory, gt: Trajectory, *, max_diff: float = 0.02, with_scale: bool = False,
                        return_alignment: bool = False) -> dict:
    """ATE and RPE of ``est`` against ``gt`` (both camera-to-world, keyed by timestamp in seconds).

    Returns {ate_rmse_m, ate_mean_m, ate_max_m, rpe_trans_m, rpe_rot_deg, n_matched, scale}; with
    ``return_alignment`` also ``T_gt_est`` (the 4x4 alignment; the estimate's frame to the ground truth's) and
    ``matched`` (matched timestamps of est). Raises ValueError with fewer than 3 matched poses.
    """
    ts_e, P = as_arrays(est)
    ts_g, Q = as_arrays(gt)
    ie, ig = associate_stamps(ts_e, ts_g, max_diff)
    if len(ie) < 3:
        raise ValueError(f"trajectory_accuracy: only {len(ie)} poses matched within {max_diff} s "
                         f"({len(ts_e)} estimated, {len(ts_g)} ground truth); need at least 3")
    P, Q = P[ie], Q[ig]
    T, s = umeyama_alignment(P[:, :3, 3], Q[:, :3, 3], with_scale=with_scale)
    aligned = (s * P[:, :3, 3]) @ T[:3, :3].T + T[:3, 3]
    err = np.linalg.norm(aligned - Q[:, :3, 3], axis=1)
    # RPE between consecutive matched poses: E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), scale applied to P's translation.
    Ps = P.copy()
    Ps[:, :3, 3] *= s
    dP = np.linalg.inv(Ps[:-1]) @ Ps[1:]
    dQ = np.linalg.inv(Q[:-1]) @ Q[1:]
    E = np.linalg.inv(dQ) @ dP
    out = {
        "ate_rmse_m": float(np.sqrt(np.mean(err ** 2))),
        "ate_mean_m": float(err.mean()),
        "ate_max_m": float(err.max()),
        "rpe_trans_m": float(np.sqrt(np.mean(np.sum(E[:, :3, 3] ** 2, axis=1)))),
        "rpe_rot_deg": float(np.sqrt(np.mean(_angle_deg(E[:, :3, :3]) ** 2))),
        "n_matched": int(len(ie)),
        "scale": float(s),
    }
    if return_alignment:
        out["T_gt_est"] = T
        out["matched"] = ts_e[ie]
    return out


def plot_trajectories(path: str | Path, trajectories: Mapping[str, Trajectory], *, reference: str | None = None,
                      max_diff: float = 0.02, title: str = "") -> Path:
    """Write a PNG top view of several trajectories (camera centres), each aligned to ``reference`` if given.

    "Top view" is the plane of the two principal axes of the reference (or first) trajectory's centres, so
    it works whatever the dataset's up axis is. matplotlib is imported here (it is only needed for plots).
    """
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - matplotlib is a core dependency
        raise ImportError("plot_trajectories needs matplotlib: pip install matplotlib") from e
    names = list(trajectories)
    if not names:
        raise ValueError("plot_trajectories: no trajectories given")
    ref = reference if reference is not None else names[0]
    ts_r, P_r = as_arrays(trajectories[ref])
    centres = {}
    for name in names:
        ts, P = as_arrays(trajectories[name])
        c = P[:, :3, 3]
        if name != ref:
            ie, ir = associate_stamps(ts, ts_r, max_diff)
            if len(ie) >= 3:
                T, _ = umeyama_alignment(c[ie], P_r[ir, :3, 3])
                c = c @ T[:3, :3].T + T[:3, 3]
        centres[name] = c
    c_ref = centres[ref]
    mu = c_ref.mean(0)
    _, _, Vt = np.linalg.svd(c_ref - mu) if len(c_ref) >= 2 else (None, None, np.eye(3))
    fig, ax = plt.subplots(figsize=(6, 6))
    for name in names:
        xy = (centres[name] - mu) @ Vt[:2].T
        ax.plot(xy[:, 0], xy[:, 1], "-" if name == ref else "-", lw=2.0 if name == ref else 1.2,
                color="k" if name == ref else None, label=name)
        ax.plot(xy[:1, 0], xy[:1, 1], "o", color=ax.lines[-1].get_color(), ms=4)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("principal axis 1 [m]")
    ax.set_ylabel("principal axis 2 [m]")
    ax.set_title(title or f"camera centres, top view (aligned to {ref})")
    ax.grid(True, alpha=0.3)
    ax.legend()
    path = Path(path)
    from ..io.atomic import atomic_write

    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110, bbox_inches="tight"))
    finally:
        plt.close(fig)
