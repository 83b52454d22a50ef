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
    with it, their Adam moments carried along; returns how many rows moved. One pass over the map whatever the
    number of keyframes moved: each row finds its keyframe's motion by a sorted look-up."""
    if not moves or len(gmap) == 0:
        return 0
    means, quats = gmap.params["means"], gmap.params["quats"]
    keys = sorted(int(k) for k in moves)
    R, t, L = _motions([moves[k] for k in keys])
    anchors = gmap.anchors
    table = torch.as_tensor(keys, dtype=anchors.dtype, device=anchors.device)
    slot = torch.searchsorted(table, anchors).clamp_(max=len(keys) - 1)
    rows = torch.nonzero(table[slot] == anchors).squeeze(1)
    if rows.numel() == 0:
        return 0
    slot = slot[rows]
    R, t = R.to(means)[slot], t.to(means)[slot]
    L = L.to(quats)[slot]
    RR, LL = R * R, L * L

    def turn(M: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return torch.bmm(M, x.unsqueeze(2)).squeeze(2)

    m_means, v_means = gmap.adam.exp_avg["means"], gmap.adam.exp_avg_sq["means"]
    m_quats, v_quats = gmap.adam.exp_avg["quats"], gmap.adam.exp_avg_sq["quats"]
    means[rows] = turn(R, means[rows]) + t
    quats[rows] = turn(L, quats[rows])
    m_means[rows] = turn(R, m_means[rows])
    v_means[rows] = turn(RR, v_means[rows])
    m_quats[rows] = turn(L, m_quats[rows])
    v_quats[rows] = turn(LL, v_quats[rows])
    gmap.touched()
    return int(rows.numel())


def _motions(moves: list[tuple[np.ndarray, np.ndarray]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per move ``(before, after)``: the rotation [3, 3] and translation [3] of ``D = after @ inv(before)`` and
    the quaternion left-multiplication matrix [4, 4] of its rotation (float64, stacked)."""
    R, t, L = [], [], []
    for before, after in moves:
        D = np.asarray(after, dtype=np.float64) @ np.linalg.inv(np.asarray(before, dtype=np.float64))
        x, y, z, w = rotmat_to_quat(D[:3, :3])
        R.append(D[:3, :3])
        t.append(D[:3, 3])
        L.append(left_quat_matrix(np.array([w, x, y, z])))
    return torch.from_numpy(np.stack(R)), torch.from_numpy(np.stack(t)), torch.from_numpy(np.stack(L))
