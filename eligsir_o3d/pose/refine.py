"""Per-training-view pose refinement, learned jointly with the map (the paper's "alignment").

Real recordings carry pose errors of a few millimetres and a few tenths of a degree per frame (KinectFusion
tracking on 7-Scenes, an SfM reconstruction on SUN3D), i.e. several pixels at 640x480: every training view then
pulls the map a little elsewhere and the map blurs. Each retained training view gets a small SE(3) correction
``xi = (omega, v)`` in its camera frame, ``T' = T @ exp(xi)``, optimised with the map by the same supervision
loss, with its own Adam moments and an L2 pull toward the identity (the given pose).

Held-out views are never refined (their images never reach the map). ``heldout_pose`` brings a held-out view's
given pose into the refined frame by one of three rules (``pose_refine.heldout_poses``), using training views only:
"carried" (``carried_pose``): the world-frame corrections ``T_a exp(xi_a) T_a^-1`` of the refined training
views just before and after it (by frame index) are interpolated and applied to its given pose; "aligned"
(default, ``alignment``): one rigid motion fitted from the refined views' given to their refined poses, the paper's
"training-pose alignment" (its Table IV renders the original held-out poses after aligning the refined training
poses); "given": as it is. Measured on real recordings the corrections drift along the trajectory, so one rigid
motion removes little of a held-out pose's error and the local rule removes most of it.

The view is rendered at its refined pose; the map's means and rotations pass through a probe (``_PoseProbe``) that
is the identity forward and, in the update's backward, sums the gradients the renderer returns for them into the
gradient of a right perturbation of the pose. The correction thus costs two small matrix products over the
Gaussians per update, on every renderer (each differentiates means and rotations), and the renderer's pose stays a
plain matrix; the per-view algebra (Rodrigues, Adam on the 6-vector) is numpy.
Off by default (config ``pose_refine.enabled``: it did not help at the true poses or at the paper's rule, lab:
pose-refine-off); with it off nothing is computed.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch


# the paper's rule first: it is the headline figure; "carried" is the figure in the map's refined frame
HELDOUT_POSE_RULES = ("aligned", "carried", "given")


def _check_rule(rule: str) -> str:
    if rule not in HELDOUT_POSE_RULES:
        raise ValueError(f"pose_refine.heldout_poses: unknown held-out pose rule {rule!r}; "
                         f"choose from {', '.join(HELDOUT_POSE_RULES)}")
    return rule


@dataclass
class PoseRefineConfig:
    enabled: bool = False
    """Learn a small SE(3) correction per training view with the map (off: the given poses; lab: pose-refine-off)."""
    lr: float = 1e-3
    """Adam step on the correction ``xi`` (radians for omega, metres for v)."""
    reg: float = 1.0
    """Loss weight of ``|xi|^2``, the pull toward the given pose (per rad^2 and per m^2)."""
    min_updates: int = 10
    """A view's pose moves only after it has supervised this many updates (the map settles first)."""
    centred: bool = False
    """Hold the views' mean correction (in the world frame) at zero so the map cannot drift."""
    heldout_poses: str = "aligned"
    """Held-out poses in the refined frame: ``aligned`` (the paper's rule), ``carried`` or ``given``."""
    warm_start: bool = False
    """A new view starts at its refined predecessor's correction instead of the given pose."""


def _rot_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (angles below pi; exact to rounding at small angles)."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0  # sin(th) * axis
    s = float(np.linalg.norm(w))
    th = float(np.arctan2(s, (np.trace(R) - 1.0) / 2.0))
    return w if s < 1e-12 else w * (th / s)


def _rot_exp(w) -> np.ndarray:
    """Rotation matrix of the axis-angle vector ``w`` (Rodrigues, float64, smooth at 0). The per-update pose
    algebra is numpy on 3-vectors: small torch ops cost ~10x more here."""
    w = np.asarray(w, dtype=np.float64)
    th2 = float(w @ w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-12:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = np.sqrt(th2)
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    return np.eye(3) + a * K + b * (K @ K)


class _PoseProbe(torch.autograd.Function):
    """Identity on (means, quats) whose backward also returns the loss gradient with respect to a right
    perturbation ``delta = (omega, v)`` of the camera pose the map was rendered at, ``T' exp(delta)`` at 0.

    Rendering at ``T' exp(delta)`` is rendering the map moved by ``M^-1``, ``M = T' exp(delta) T'^-1``: to first
    order ``x -> x - w x (x - c) - t`` with ``w = R' omega``, ``t = R' v`` and ``c`` the camera centre, and every
    orientation left-multiplied by the quaternion ``(1, -w / 2)``. So the gradient is a sum over the Gaussians of
    the gradients the renderer already returns: ``dL/dt = -sum g_m``, ``dL/dw = -sum (x - c) x g_m
    - 1/2 sum (q_w g_u - g_w q_u + q_u x g_u)``, rotated into the camera frame by ``R'^T``. The forward costs
    nothing; the backward takes the sums from ``x^T g_m`` and ``q^T g_q`` (two small matrix products), finishes in
    numpy and leaves the result in ``sink.grad`` (a ``_PoseGrad``); the map's gradients pass through unchanged."""

    @staticmethod
    def forward(ctx, means, quats, sink):
        ctx.save_for_backward(means, quats)
        ctx.sink = sink
        return means.view_as(means), quats.view_as(quats)

    @staticmethod
    def backward(ctx, g_means, g_quats):
        means, quats = ctx.saved_tensors
        z = means.new_zeros(16)  # sum (x - c) x g = vee(M - M^T) - c x sum g with M = x^T g (3 x N x 3), and
        M = means.T @ g_means if g_means is not None else z[:9].reshape(3, 3)  # the rotations' sum from Q = q^T g
        g_sum = g_means.sum(0) if g_means is not None else z[:3]
        Q = quats.T @ g_quats if g_quats is not None else z.reshape(4, 4)
        small = torch.cat([M.reshape(-1), g_sum, Q.reshape(-1)]).detach().cpu().numpy().astype(np.float64)
        M, g_sum, Q = small[:9].reshape(3, 3), small[9:12], small[12:].reshape(4, 4)
        sink = ctx.sink
        c = sink.c
        c_x_g = np.array([c[1] * g_sum[2] - c[2] * g_sum[1], c[2] * g_sum[0] - c[0] * g_sum[2],
                          c[0] * g_sum[1] - c[1] * g_sum[0]])  # np.cross costs ~25 us on 3-vectors
        w_world = c_x_g - _vee(M) - 0.5 * (Q[0, 1:] - Q[1:, 0] + _vee(Q[1:, 1:]))
        sink.grad = np.concatenate([sink.R.T @ w_world, -sink.R.T @ g_sum])
        return g_means, g_quats, None


class _PoseGrad:
    """Where ``_PoseProbe`` leaves the pose gradient: the rendered pose's rotation ``R`` and centre ``c``, and
    ``grad`` (float64 (omega, v); None until the backward ran)."""

    def __init__(self, T: np.ndarray):
        T = np.asarray(T, dtype=np.float64)
        self.R, self.c, self.grad = T[:3, :3], T[:3, 3], None


def _vee(M: np.ndarray) -> np.ndarray:
    """(M12 - M21, M20 - M02, M01 - M10): for M = sum_i a_i b_i^T this is sum_i a_i x b_i."""
    return np.array([M[1, 2] - M[2, 1], M[2, 0] - M[0, 2], M[0, 1] - M[1, 0]])


class PoseRefiner:
    """Per-view SE(3) corrections (keyed by frame index) with their own Adam moments."""

    def __init__(self, cfg: PoseRefineConfig, device: torch.device | str = "cpu"):
        _check_rule(cfg.heldout_poses)
        self.cfg = cfg
        self.device = torch.device(device)
        self.state: dict[int, dict] = {}  # index -> {"xi", "m", "v", "t", "seen"}
        self._live: tuple[int, _PoseGrad] | None = None

    @property
    def active(self) -> bool:
        return bool(self.cfg.enabled)

    @property
    def moved(self) -> bool:
        """Whether any view's pose has been refined (the map then lives in the refined frame)."""
        return self.active and any(s["t"] > 0 for s in self.state.values())

    @property
    def carries(self) -> bool:
        """Whether held-out views are rendered at poses moved into the refined frame (``heldout_poses`` is not
        "given" and some view has moved)."""
        return self.moved and self.cfg.heldout_poses != "given"

    def heldout_pose(self, index: int, T_world_cam: np.ndarray, rule: str | None = None) -> np.ndarray:
        """The pose a held-out view (frame ``index``, given pose ``T_world_cam``) is rendered at, by ``rule``
        (default: ``heldout_poses``): "carried", "aligned" or "given"."""
        rule = _check_rule(self.cfg.heldout_poses if rule is None else rule)
        if not self.moved or rule == "given":
            return np.asarray(T_world_cam, dtype=np.float64)
        if rule == "aligned":
            return self.alignment() @ np.asarray(T_world_cam, dtype=np.float64)
        return self.carried_pose(index, T_world_cam, always=True)

    def alignment(self) -> np.ndarray:
        """T_refined_given: the one rigid motion that best takes the refined views' given poses onto their refined
        poses (rotation from all orientations, then the mean translation; ``pose.accuracy.pose_alignment``)."""
        from .accuracy import pose_alignment

        views = [s for s in self.state.values() if s["t"] > 0 and "T" in s]
        if not views:
            return np.eye(4)
        given = [s["T"].numpy() for s in views]
        return pose_alignment(given, [T @ self._delta(s["xi"]) for T, s in zip(given, views)])

    @staticmethod
    def _delta(xi: torch.Tensor) -> np.ndarray:
        D = np.eye(4)
        x = xi.numpy() if torch.is_tensor(xi) else np.asarray(xi)
        D[:3, :3] = _rot_exp(x[:3])
        D[:3, 3] = x[3:]
        return D

    def correction(self, index: int) -> torch.Tensor:
        """The view's current xi (zeros for a view never refined)."""
        s = self.state.get(int(index))
        return torch.zeros(6) if s is None else s["xi"].detach().clone()

    def pose(self, frame) -> np.ndarray:
        """``frame``'s refined T_world_cam (its given pose when refinement is off or has not moved it)."""
        return np.asarray(frame.T_world_cam) @ self._delta(self.correction(frame.index))

    def _world_correction(self, s: dict) -> tuple[np.ndarray, np.ndarray]:
        """A refined view's correction in world terms: the refined pose is [R Rc, t + R v] = a rotation
        R Rc R^T about the camera centre followed by a shift R v of the centre; returns (axis-angle of R Rc R^T, R v)."""
        R = s["R"].numpy()
        Rc = _rot_exp(s["xi"][:3].numpy())
        return _rot_log(R @ Rc @ R.T), R @ s["xi"][3:].numpy()

    def carried_pose(self, index: int, T_world_cam: np.ndarray, always: bool = False) -> np.ndarray:
        """A view that is not refined (a held-out view) at its given pose ``T_world_cam``, moved into the refined
        training frame: the world-frame corrections of the refined views just before and after ``index`` (by frame
        index; the nearest one at either end) are interpolated linearly and applied about the view's own camera
        centre. Unchanged when refinement is off or no view has moved yet (``always=False``: also when held-out views
        are not carried, ``heldout_poses`` other than "carried")."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        if not (self.active and (always or self.cfg.heldout_poses == "carried")):
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
        T = torch.as_tensor(np.asarray(frame.T_world_cam), dtype=torch.float64)
        return {"xi": z.clone() if xi is None else xi, "m": z.clone(), "v": z.clone(), "t": 0, "seen": 0,
                "R": T[:3, :3].clone(), "T": T.clone()}

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
        moved.T_world_cam = np.asarray(frame.T_world_cam) @ self._delta(s["xi"])
        return moved

    def render_args(self, frame, args: tuple) -> tuple[tuple, np.ndarray]:
        """The map's render args and the pose to render ``frame`` at: its refined pose, with the args wrapped so
        that the update's backward also leaves the gradient of the view's correction (``step`` applies it).
        Off, or for a view that has not moved yet and is still settling: ``(args, frame.T_world_cam)`` as they are."""
        if not self.active:
            return args, frame.T_world_cam
        s = self.state.get(int(frame.index))
        if s is None:
            s = self.state[int(frame.index)] = self._new_state(frame)
        s["seen"] += 1
        T = self.pose(frame) if s["xi"].any() else frame.T_world_cam
        if s["seen"] <= self.cfg.min_updates:  # the map settles first; a warm-started correction already applies
            self._live = None
            return args, T
        means, quats, *rest = args
        if not (means.requires_grad or quats.requires_grad):  # a frozen map (localisation): the pose still learns
            means = means.detach().requires_grad_(True)
        sink = _PoseGrad(T)
        self._live = (int(frame.index), sink)
        return (*_PoseProbe.apply(means, quats, sink), *rest), T

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step on the rendered view's correction, from the gradient its probe left in the update's
        backward plus that of ``reg * |xi|^2``; the step is composed on the right: ``exp(xi) <- exp(xi) exp(step)``."""
        if self._live is None:
            return
        index, sink = self._live
        self._live = None
        if sink.grad is None:
            return
        s = self.state[index]
        xi, m, v = s["xi"].numpy(), s["m"].numpy(), s["v"].numpy()  # float64 views: numpy on 6-vectors is cheap
        g = sink.grad + 2.0 * self.cfg.reg * xi
        b1, b2, eps = 0.9, 0.999, 1e-15
        s["t"] += 1
        m *= b1
        m += (1 - b1) * g
        v *= b2
        v += (1 - b2) * g * g
        d = -self.cfg.lr * (m / (1 - b1 ** s["t"])) / (np.sqrt(v / (1 - b2 ** s["t"])) + eps)
        Rc = _rot_exp(xi[:3])
        s["xi"] = torch.from_numpy(np.concatenate([_rot_log(Rc @ _rot_exp(d[:3])), xi[3:] + Rc @ d[3:]]))
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
        return {str(k): {n: v.clone() if torch.is_tensor(v) else int(v) for n, v in s.items()}
                for k, s in self.state.items()}

    def load_state_dict(self, state: dict | None) -> None:
        """Restore ``state_dict``'s output (a checkpoint from before the given pose was kept lacks "T": such
        views take no part in ``alignment``)."""
        self.state = {int(k): {n: int(v) if n in ("t", "seen") else torch.as_tensor(v, dtype=torch.float64).clone()
                               for n, v in s.items()} for k, s in (state or {}).items()}
        self._live = None
