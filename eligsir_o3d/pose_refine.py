"""Per-training-view pose refinement, learned jointly with the map (issue 16, "alignment").

Real recordings carry pose errors of a few millimetres and a few tenths of a degree per frame (KinectFusion
tracking on 7-Scenes, an SfM reconstruction on SUN3D), i.e. several pixels at 640x480: every training view then
pulls the map a little elsewhere and the map blurs. Each retained training view gets a small SE(3) correction
``xi = (omega, v)`` in its camera frame, ``T' = T @ exp(xi)``, optimised with the map by the same supervision
loss, with its own Adam moments and an L2 pull toward the identity (the given pose).

Held-out views are never refined (their images never reach the map). Their given poses are carried into the
refined frame the way the training trajectory was (``carried_pose``): the world-frame correction
``T_a exp(xi_a) T_a^-1`` of the refined training views just before and after the view (by frame index) is
interpolated and applied to the given pose. This is a local form of the paper's "training-pose alignment" (its
Table IV renders the original held-out poses after aligning the refined training poses): it uses only training
views, and the given pose's drift is what it removes. ``carry_to_heldout=False`` renders the given poses as they are.

The correction is applied to the Gaussians rather than to the camera (``corrected_args``): rendering the moved
Gaussians at ``T`` is rendering the map at ``T @ exp(xi)``, so the gradient reaches ``xi`` through any renderer
that differentiates means and rotations (every backend here does), and the renderer's pose stays a plain matrix.
On by default (config ``pose_refine.enabled``); with it off nothing is computed.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class PoseRefineConfig:
    enabled: bool = True
    # the best of the settings measured in issue 16 on the 7-Scenes kitchen and the SUN3D study room, with held-out
    # views carried (lr 2e-4 / 5e-4 / 1e-3 / 3e-3, reg 0 / 1 / 10 / 100, min_updates 0 / 10, warm start on / off)
    lr: float = 1e-3  # Adam step on xi (radians for omega, metres for v)
    reg: float = 1.0  # loss weight of |xi|^2 (pull toward the given pose); units: per rad^2 / m^2
    min_updates: int = 10  # a view's pose moves only after it has supervised this many updates (map settles first)
    centred: bool = False  # hold the views' mean correction (in the world frame) at zero: the map cannot drift
    carry_to_heldout: bool = True  # render a held-out view at its given pose moved by its neighbours' corrections
    warm_start: bool = False  # a new view starts at its refined predecessors' correction (not at the given pose)


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the axis-angle vector ``w`` (Rodrigues; smooth at 0)."""
    th2 = (w * w).sum()
    th = torch.sqrt(th2 + 1e-24)
    K = _skew(w)
    small = th2 < 1e-12
    a = torch.where(small, 1.0 - th2 / 6.0, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / (th2 + 1e-24))
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * K + b * (K @ K)


def _axis_quat(w: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (wxyz) of the axis-angle vector ``w``."""
    th = torch.sqrt((w * w).sum() + 1e-24)
    return torch.cat([torch.cos(th / 2).reshape(1), (torch.sin(th / 2) / th) * w])


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _rot_quat(R: np.ndarray) -> np.ndarray:
    """wxyz quaternion of a rotation matrix (Shepperd's method, any rotation)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def _rot_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (angles below pi)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return w if th < 1e-8 else w * (th / np.sin(th))


def _rot_exp(w: np.ndarray) -> np.ndarray:
    return so3_exp(torch.as_tensor(w, dtype=torch.float64)).numpy()


def _left_matrix(p: torch.Tensor) -> torch.Tensor:
    """The 4x4 matrix of quaternion left-multiplication: ``quat_mul(p, q) == q @ _left_matrix(p).T``."""
    pw, px, py, pz = p.unbind(-1)
    return torch.stack([torch.stack([pw, -px, -py, -pz]), torch.stack([px, pw, -pz, py]),
                        torch.stack([py, pz, pw, -px]), torch.stack([pz, -py, px, pw])])


def corrected_args(args: tuple, T_world_cam: np.ndarray, xi: torch.Tensor) -> tuple:
    """``args`` (means, quats, scales, opacities, colors) moved so that rendering them at ``T_world_cam`` is
    rendering the original map at ``T_world_cam @ exp(xi)``; ``xi`` = (omega, v) in the camera frame.

    The move is one rigid motion of the world, so it is applied as one [N, 3] x [3, 3] and one [N, 4] x [4, 4]
    product (row vectors): means ``m A + b`` with ``A = R Rc R^T`` (as a right factor) and ``b = t - t A - v Rc R^T``,
    quaternions left-multiplied by the world rotation ``R Rc^T R^T``. Per Gaussian that is two small matrix
    products forward and two backward, so a refined update costs little more than a plain one."""
    means, quats, scales, opacities, colors = args
    dev, dt = means.device, means.dtype
    R = torch.as_tensor(np.asarray(T_world_cam)[:3, :3], dtype=dt, device=dev)
    t = torch.as_tensor(np.asarray(T_world_cam)[:3, 3], dtype=dt, device=dev)
    xi = xi.to(dev, dt)
    w, v = xi[:3], xi[3:]
    RcRt = so3_exp(w) @ R.T
    A = R @ RcRt
    b = t - t @ A - v @ RcRt
    qR = torch.as_tensor(_rot_quat(T_world_cam[:3, :3]), dtype=dt, device=dev)
    qR_inv = qR * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=dt, device=dev)
    qM = quat_mul(quat_mul(qR, _axis_quat(-w)), qR_inv)  # the world rotation R Rc^T R^T
    return means @ A + b, quats @ _left_matrix(qM).T, scales, opacities, colors


class PoseRefiner:
    """Per-view SE(3) corrections (keyed by frame index) with their own Adam moments."""

    def __init__(self, cfg: PoseRefineConfig, device: torch.device | str = "cpu"):
        self.cfg = cfg
        self.device = torch.device(device)
        self.state: dict[int, dict] = {}  # index -> {"xi", "m", "v", "t", "seen"}
        self._live: tuple[int, torch.Tensor] | None = None

    @property
    def active(self) -> bool:
        return bool(self.cfg.enabled)

    @property
    def carries(self) -> bool:
        """Whether held-out views are rendered at carried poses (refinement on, ``carry_to_heldout``, views moved)."""
        return self.active and self.cfg.carry_to_heldout and any(s["t"] > 0 for s in self.state.values())

    def correction(self, index: int) -> torch.Tensor:
        """The view's current xi (zeros for a view never refined)."""
        s = self.state.get(int(index))
        return torch.zeros(6) if s is None else s["xi"].detach().clone()

    def pose(self, frame) -> np.ndarray:
        """``frame``'s refined T_world_cam (its given pose when refinement is off or has not moved it)."""
        xi = self.correction(frame.index).double()
        D = np.eye(4)
        D[:3, :3] = so3_exp(xi[:3]).numpy()
        D[:3, 3] = xi[3:].numpy()
        return np.asarray(frame.T_world_cam) @ D

    def _world_correction(self, s: dict) -> tuple[np.ndarray, np.ndarray]:
        """A refined view's correction in world terms: the refined pose is [R Rc, t + R v] = a rotation
        R Rc R^T about the camera centre followed by a shift R v of the centre; returns (axis-angle of R Rc R^T, R v)."""
        R = s["R"].numpy()
        Rc = so3_exp(s["xi"][:3]).numpy()
        return _rot_log(R @ Rc @ R.T), R @ s["xi"][3:].numpy()

    def carried_pose(self, index: int, T_world_cam: np.ndarray, always: bool = False) -> np.ndarray:
        """A view that is not refined (a held-out view) at its given pose ``T_world_cam``, moved into the refined
        training frame: the world-frame corrections of the refined views just before and after ``index`` (by frame
        index; the nearest one at either end) are interpolated linearly and applied about the view's own camera
        centre. Unchanged when refinement is off, ``carry_to_heldout`` is False or no view has moved yet."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        if not (self.active and (always or self.cfg.carry_to_heldout)):
            return T
        keys = sorted(k for k, s in self.state.items() if s["t"] > 0)
        if not keys:
            return T
        pos = int(np.searchsorted(keys, index))
        a, b = keys[max(pos - 1, 0)], keys[min(pos, len(keys) - 1)]
        wa = 1.0 if a == b else (b - index) / (b - a)
        ra, ta = self._world_correction(self.state[a])
        rb, tb = self._world_correction(self.state[b])
        r, t = wa * ra + (1 - wa) * rb, wa * ta + (1 - wa) * tb
        out = T.copy()
        out[:3, :3] = _rot_exp(r) @ T[:3, :3]
        out[:3, 3] = T[:3, 3] + t
        return out

    def _new_state(self, frame, xi: torch.Tensor | None = None) -> dict:
        z = torch.zeros(6, dtype=torch.float64)
        return {"xi": z.clone() if xi is None else xi, "m": z.clone(), "v": z.clone(), "t": 0, "seen": 0,
                "R": torch.as_tensor(np.asarray(frame.T_world_cam)[:3, :3], dtype=torch.float64)}

    def warm_start(self, frame) -> None:
        """Start a new training view at the correction its refined predecessors imply (``carried_pose``), so
        that its first updates and its new Gaussians already sit in the refined frame (``cfg.warm_start``)."""
        if not (self.active and self.cfg.warm_start) or int(frame.index) in self.state:
            return
        T = np.asarray(frame.T_world_cam, dtype=np.float64)
        D = np.linalg.inv(T) @ self.carried_pose(frame.index, T, always=True)
        xi = torch.as_tensor(np.concatenate([_rot_log(D[:3, :3]), D[:3, 3]]), dtype=torch.float64)
        self.state[int(frame.index)] = self._new_state(frame, xi)

    def posed(self, frame):
        """``frame`` itself, or a shallow copy at its refined pose once it has a correction (what growth
        back-projects with, so new Gaussians land where the view's render shows the holes)."""
        s = self.state.get(int(frame.index)) if self.active else None
        if s is None or not s["xi"].any():
            return frame
        moved = copy.copy(frame)
        moved.T_world_cam = self.pose(frame)
        return moved

    def render_args(self, frame, args: tuple) -> tuple:
        """The map's render args as seen from ``frame``'s refined pose (unchanged when off)."""
        if not self.active:
            return args
        s = self.state.get(int(frame.index))
        if s is None:
            s = self.state[int(frame.index)] = self._new_state(frame)
        s["seen"] += 1
        if s["seen"] <= self.cfg.min_updates:  # the map settles first; a warm-started correction already applies
            self._live = None
            return corrected_args(args, frame.T_world_cam, s["xi"].float()) if s["xi"].any() else args
        xi = s["xi"].to(torch.float32).clone().requires_grad_(True)
        self._live = (int(frame.index), xi)
        return corrected_args(args, frame.T_world_cam, xi)

    def regulariser(self) -> torch.Tensor | None:
        """``reg * |xi|^2`` of the view being rendered (None when nothing is refined this update)."""
        if self._live is None or self.cfg.reg <= 0:
            return None
        xi = self._live[1]
        return self.cfg.reg * (xi * xi).sum()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step on the rendered view's xi, from the gradient the update's backward left on it."""
        if self._live is None:
            return
        index, xi = self._live
        self._live = None
        if xi.grad is None:
            return
        s = self.state[index]
        g = xi.grad.to(torch.float64)
        b1, b2, eps = 0.9, 0.999, 1e-15
        s["t"] += 1
        s["m"].mul_(b1).add_(g, alpha=1 - b1)
        s["v"].mul_(b2).addcmul_(g, g, value=1 - b2)
        mh = s["m"] / (1 - b1 ** s["t"])
        vh = s["v"] / (1 - b2 ** s["t"])
        s["xi"] -= self.cfg.lr * mh / (vh.sqrt() + eps)
        if self.cfg.centred and len(self.state) > 1:
            self._centre()

    def _centre(self) -> None:
        """Subtract the views' mean world-frame rotation and translation correction from every view: a common
        motion of all training views is a motion of the map away from the given trajectory (and from the held-out
        views, which keep their given poses), not an alignment between views."""
        views = list(self.state.values())
        R = torch.stack([s["R"] for s in views])  # [V, 3, 3]
        xi = torch.stack([s["xi"] for s in views])  # [V, 6]
        w_world = torch.einsum("vij,vj->vi", R, xi[:, :3]).mean(0)
        t_world = torch.einsum("vij,vj->vi", R, xi[:, 3:]).mean(0)
        for s in views:
            s["xi"][:3] -= s["R"].T @ w_world
            s["xi"][3:] -= s["R"].T @ t_world

    def summary(self) -> dict:
        """Median rotation (degrees) and translation (mm) of the current corrections."""
        if not self.state:
            return {"views": 0}
        xs = torch.stack([s["xi"] for s in self.state.values()])
        return {"views": len(self.state),
                "median_rot_deg": float(xs[:, :3].norm(dim=1).median()) * 180.0 / np.pi,
                "median_trans_mm": float(xs[:, 3:].norm(dim=1).median()) * 1000.0}

    def state_dict(self) -> dict:
        return {str(k): {"xi": s["xi"].clone(), "m": s["m"].clone(), "v": s["v"].clone(), "t": int(s["t"]),
                         "seen": int(s["seen"]), "R": s["R"].clone()} for k, s in self.state.items()}

    def load_state_dict(self, state: dict | None) -> None:
        self.state = {int(k): {"xi": torch.as_tensor(s["xi"], dtype=torch.float64).clone(),
                               "m": torch.as_tensor(s["m"], dtype=torch.float64).clone(),
                               "v": torch.as_tensor(s["v"], dtype=torch.float64).clone(),
                               "t": int(s["t"]), "seen": int(s["seen"]),
                               "R": torch.as_tensor(s["R"], dtype=torch.float64).clone()}
                      for k, s in (state or {}).items()}
        self._live = None
