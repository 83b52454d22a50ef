"""Gaussians that follow their keyframe: every row of a :class:`.gaussians.GaussianMap` carries an anchor (the
frame index of the keyframe that was current when it was created; a relocated copy takes its source's; -1:
none), kept aligned by the map's add, remove and assign. When loop closure moves a keyframe from pose ``A`` to
pose ``B``, its rows move rigidly by ``D = B @ inv(A)``: means ``x -> R x + t``, rotations ``q -> q_R * q``.

Adam's moments follow the same linear maps where they can: the means' first moment (a gradient average, in world
axes) is rotated by ``R``, the quaternions' by the left-multiplication matrix of ``q_R`` (orthogonal); the second
moments, per-coordinate averages of squared gradients, are carried by the squared entries of the same matrices
(exact for a rotation that permutes axes, the diagonal of ``R diag(v) R^T`` otherwise). Scales, opacities and
colours are unchanged (view-dependent colour is kept in the Gaussian's world frame: a small turn leaves it).
"""

from __future__ import annotations

import numpy as np
import torch

from .camera import rotmat_to_quat


def left_quat_matrix(q: np.ndarray) -> np.ndarray:
    """[4, 4] L with L @ p = q * p (Hamilton product, wxyz)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]], dtype=np.float64)


@torch.no_grad()
def move_anchored(gmap, moves: dict[int, tuple[np.ndarray, np.ndarray]]) -> int:
    """Move the rows anchored to each keyframe of ``moves`` (``{frame index: (pose before, pose now)}``) rigidly
    with it, their Adam moments carried along; returns how many rows moved."""
    if not moves or len(gmap) == 0:
        return 0
    anchors = gmap.anchors
    moved = 0
    means, quats = gmap.params["means"], gmap.params["quats"]
    m_means, v_means = gmap.adam.exp_avg["means"], gmap.adam.exp_avg_sq["means"]
    m_quats, v_quats = gmap.adam.exp_avg["quats"], gmap.adam.exp_avg_sq["quats"]
    for index, (before, after) in moves.items():
        rows = torch.nonzero(anchors == int(index)).squeeze(1)
        if rows.numel() == 0:
            continue
        D = np.asarray(after, dtype=np.float64) @ np.linalg.inv(np.asarray(before, dtype=np.float64))
        R = torch.as_tensor(D[:3, :3], dtype=means.dtype, device=means.device)
        t = torch.as_tensor(D[:3, 3], dtype=means.dtype, device=means.device)
        x, y, z, w = rotmat_to_quat(D[:3, :3])
        L = torch.as_tensor(left_quat_matrix(np.array([w, x, y, z])), dtype=quats.dtype, device=quats.device)
        means[rows] = means[rows] @ R.T + t
        quats[rows] = quats[rows] @ L.T
        m_means[rows] = m_means[rows] @ R.T
        v_means[rows] = v_means[rows] @ (R * R).T
        m_quats[rows] = m_quats[rows] @ L.T
        v_quats[rows] = v_quats[rows] @ (L * L).T
        moved += int(rows.numel())
    gmap.touched()
    return moved
