"""View-culled updates: an update projects, composites, steps (Adam), noises and relocates only the Gaussians that
can reach its view, so its cost follows the Gaussians in view and not the map's total.

- :func:`in_view`: the ids of the Gaussians whose screen footprint can reach a camera's image. The test bounds the
  renderer's 3-sigma radius from above (the clamped projection Jacobian's Frobenius norm times the largest scale,
  plus the low-pass, the radius formula's clamp and rounding), so every Gaussian the renderer would draw is kept
  and rendering the kept ones gives the same image and the same gradients as rendering the map (tested against
  the torch reference). On the CPU one compiled pass (:mod:`._cull_kernels`), elsewhere the same bound in torch.
- :class:`InView`: the kept rows gathered as leaf tensors (raw parameters, [M, ...]); the update renders them,
  back-propagates into them, and :meth:`InView.adam_step` applies Adam to those rows of the map only. Each row
  keeps its step count (``row_step``: the updates that stepped it since its moments were zeroed); with
  ``optim.adam.row_bias_correction`` the bias correction uses it and is exact for a Gaussian that is in view in
  a fraction of the updates; by default it uses the tensor's step count, as torch's Adam and the map-wide update
  do (larger first steps for rows seen late: -0.15 dB with the exact correction before culling, -0.4 dB on the
  kitchen with culling, seed 0). Rows outside the view are neither read nor written: parameters and moments
  stay bit for bit as they were.

On a large map the test does not read every row: from :data:`.cell_index.MIN_ROWS` (200k) rows a float32 CPU
map keeps a spatial index (:class:`.cell_index.CellIndex`, groups of nearby rows with their bounds, told of every
row an update, the noise or relocation changes) and :func:`map_in_view` tests the groups first, then the rows of
the groups that can reach the view: the same ids, in ~0.7 ms instead of ~9 ms at 1M Gaussians with 20k in view
(one core, kitchen views). Smaller maps take one pass over every row (24 bytes per Gaussian; < 2 ms at 200k).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import PARAM_NAMES, sh0_to_rgb
from .projection import EPS2D, NEAR, world_to_cam


def camera_bounds(camera: Camera, low_pass: float = EPS2D) -> np.ndarray:
    """(fx, fy, cx, cy, width, height, near, jb2, lp) float64; jb2 * s^2 / z^2 bounds the largest eigenvalue of the
    projected covariance of a Gaussian of largest scale s at depth z (the Jacobian's x/z, y/z clamped as the
    renderer clamps them, :func:`.render.projection.project`); lp: the render's ``low_pass`` plus the 0.32 px^2
    that the radius formula's clamp can add."""
    fx, fy, cx, cy, w, h = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lx = max((w - cx - 0.5) / fx, (cx + 0.5) / fx) + 0.3 * tan_x
    ly = max((h - cy - 0.5) / fy, (cy + 0.5) / fy) + 0.3 * tan_y
    jb2 = fx * fx * (1.0 + lx * lx) + fy * fy * (1.0 + ly * ly)
    return np.array([fx, fy, cx, cy, w, h, NEAR, jb2, float(low_pass) + 0.32], np.float64)


def in_view(means: torch.Tensor, log_scales: torch.Tensor, camera: Camera, T_world_cam,
            low_pass: float = EPS2D) -> torch.Tensor:
    """Ids [M] int64 (ascending, on the map's device) of the Gaussians (raw means [N, 3], log scales [N, 3]) that
    can reach ``camera``'s image at ``T_world_cam``; a superset of those the renderer draws (with ``low_pass``)."""
    cam = camera_bounds(camera, low_pass)
    V = world_to_cam(T_world_cam, "cpu", torch.float64).numpy()
    if means.device.type == "cpu" and means.dtype == torch.float32 and log_scales.dtype == torch.float32:
        from ..runtime.jit import rows_threads
        from ._cull_kernels import frustum_rows

        with rows_threads(means.shape[0]):
            rows = frustum_rows(means.detach().contiguous().numpy(), log_scales.detach().contiguous().numpy(), V, cam)
        return torch.from_numpy(rows)
    Vt = torch.as_tensor(V, device=means.device)
    p = means.detach().double() @ Vt[:3, :3].T + Vt[:3, 3]
    x, y, z = p.unbind(-1)
    front = z > cam[6]
    zs = torch.where(front, z, torch.ones_like(z))
    s = torch.exp(log_scales.detach().double().amax(-1).clamp(max=80.0))
    r = 3.0 * torch.sqrt(s * s * cam[7] / (zs * zs) + cam[8]) * 1.001 + 2.0
    u, v = cam[0] * x / zs + cam[2], cam[1] * y / zs + cam[3]
    hit = front & (u + r > -0.5) & (u - r < cam[4] - 0.5) & (v + r > -0.5) & (v - r < cam[5] - 0.5)
    return torch.nonzero(hit).squeeze(1)


def map_in_view(gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> torch.Tensor:
    """:func:`in_view` of a map's rows; a float32 CPU map of :data:`.cell_index.MIN_ROWS` rows or more keeps a
    spatial index (:class:`.cell_index.CellIndex`) for it, which returns the same ids."""
    from .cell_index import MIN_ROWS, CellIndex

    means, log_scales = gmap.params["means"], gmap.params["scales"]
    if len(gmap) < MIN_ROWS or means.device.type != "cpu" or means.dtype != torch.float32 or \
            log_scales.dtype != torch.float32:
        gmap.row_index = None
        return in_view(means, log_scales, camera, T_world_cam, low_pass)
    if gmap.row_index is None:
        gmap.row_index = CellIndex(gmap)
    V = world_to_cam(T_world_cam, "cpu", torch.float64).numpy()
    return torch.from_numpy(gmap.row_index.rows(V, camera_bounds(camera, low_pass)))


class InView:
    """The rows ``idx`` [M] of ``gmap`` one update supervises, as leaf tensors of their raw parameters."""

    def __init__(self, gmap, idx: torch.Tensor):
        self.gmap = gmap
        self.idx = idx.to(gmap.device)
        self.n_map = len(gmap)
        self.leaves = self._gather(gmap, self.idx)

    @staticmethod
    def _gather(gmap, idx: torch.Tensor) -> dict:
        """The rows ``idx`` of every raw parameter, as new leaf tensors that require grad: on the CPU for float32
        contiguous parameters one compiled pass over the rows for all of them (torch's indexing is one call per
        parameter, ~50 us each at a few thousand rows), elsewhere torch's indexing."""
        params = [gmap.params[n].detach() for n in PARAM_NAMES]
        if idx.device.type != "cpu" or any(p.dtype != torch.float32 or not p.is_contiguous() for p in params):
            return {n: p[idx].requires_grad_(True) for n, p in zip(PARAM_NAMES, params)}
        from ..runtime.jit import rows_threads
        from ._cull_kernels import _gather_view

        outs = [torch.empty((idx.numel(),) + tuple(p.shape[1:]), dtype=torch.float32) for p in params]
        widths = [p[0].numel() if len(p) else 0 for p in params]  # shN of degree 0: width 0
        with rows_threads(idx.numel()):
            _gather_view(tuple(p.view(len(p), w).numpy() for p, w in zip(params, widths)), idx.numpy(),
                         tuple(o.view(idx.numel(), w).numpy() for o, w in zip(outs, widths)))
        return {n: o.requires_grad_(True) for n, o in zip(PARAM_NAMES, outs)}

    @classmethod
    def select(cls, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> "InView":
        return cls(gmap, map_in_view(gmap, camera, T_world_cam, low_pass))

    def __len__(self) -> int:
        return int(self.idx.numel())

    def render_args(self) -> tuple:
        """:meth:`.gaussians.GaussianMap.render_args` of the kept rows (activated units, differentiable)."""
        lv = self.leaves
        if self.gmap.sh_degree == 0:
            colors = torch.clamp_min(sh0_to_rgb(lv["sh0"][:, 0]), 0.0)
        else:
            colors = torch.cat([lv["sh0"], lv["shN"]], 1)
        return lv["means"], lv["quats"], torch.exp(lv["scales"]), torch.sigmoid(lv["opacities"]), colors

    def regulariser(self, opacity_reg: float, scale_reg: float) -> torch.Tensor | None:
        """3DGS-MCMC's ``opacity_reg * mean(opacity) + scale_reg * mean(scale)`` over the map, with the rows out
        of view held constant: the kept rows get the gradient the map-wide mean gives them (1 / N each)."""
        if self.n_map == 0 or len(self) == 0 or (opacity_reg <= 0 and scale_reg <= 0):
            return None
        lv = self.leaves
        return (opacity_reg * torch.sigmoid(lv["opacities"]).sum()
                + scale_reg * torch.exp(lv["scales"]).sum() / 3.0) / self.n_map

    @torch.no_grad()
    def adam_step(self) -> None:
        """Adam on the kept rows of every parameter whose leaf received a gradient; per-row step counts. Float32 on
        the CPU: one compiled pass for the step and the rows' bookkeeping (:func:`._cull_kernels._adam_view`);
        elsewhere the same in torch."""
        gmap, idx = self.gmap, self.idx
        if len(gmap) != self.n_map:
            raise RuntimeError(f"the map changed size ({self.n_map} -> {len(gmap)}) between render and step")
        todo = [(n, gmap.params[n], self.leaves[n].grad) for n in PARAM_NAMES]  # "means" first: its row_seen
        todo = [(n, p, g) for n, p, g in todo if g is not None and p.numel() > 0]  # is every row's age in updates
        gmap.touched(idx)
        if gmap.device.type == "cpu" and all(p.dtype == g.dtype == torch.float32 for _, p, g in todo):
            self._adam_compiled(todo)
        else:
            self._adam_torch(todo)

    def _row_state(self, name: str, p: torch.Tensor) -> dict:
        """Adam's state of ``p`` with its per-row counters (``row_step``; ``row_seen`` for the means)."""
        from ..optim.update_kernels import adam_state

        state = adam_state(self.gmap.optimizers[name], p)
        for key in ("row_step",) + (("row_seen",) if name == "means" else ()):
            if key not in state:  # a state without rows (torch's Adam, a checkpoint): count from now
                state[key] = torch.zeros(len(self.gmap), dtype=torch.float32, device=p.device)
        return state

    def _adam_compiled(self, todo) -> None:
        gmap, idx, cfg = self.gmap, self.idx, self.gmap.adam
        ps, gs, ms, vs, rss, hyper, steps, widths = [], [], [], [], [], [], [], []
        seen = None
        for name, p, g in todo:
            group = gmap.optimizers[name].param_groups[0]
            b1, b2 = group["betas"]
            state = self._row_state(name, p)
            if name == "means":
                seen = state["row_seen"].numpy()
            state["step"] += 1
            ps.append(p.detach().view(-1).numpy())
            gs.append(g.contiguous().view(-1).numpy())
            ms.append(state["exp_avg"].view(-1).numpy())
            vs.append(state["exp_avg_sq"].view(-1).numpy())
            rss.append(state["row_step"].numpy())
            hyper.append((1.0 - b1, b2, 1.0 - b2, group["eps"], group["lr"], b1))
            steps.append(float(state["step"]))
            widths.append(p.numel() // max(p.shape[0], 1))
        if not ps:
            return
        from ..runtime.jit import rows_threads
        from ._cull_kernels import _adam_view

        plan = np.array([float(cfg.row_bias_correction), cfg.means_decay_to, cfg.means_decay_updates,
                         cfg.warmup_updates, float(seen is not None)], np.float64)
        with rows_threads(len(idx)):
            _adam_view(tuple(ps), tuple(gs), tuple(ms), tuple(vs), tuple(rss), np.array(hyper, np.float64),
                       np.array(steps, np.float64), np.array(widths, np.int64), idx.numpy(),
                       np.zeros(1, np.float32) if seen is None else seen, plan)

    def _adam_torch(self, todo) -> None:
        gmap, idx, cfg = self.gmap, self.idx, self.gmap.adam
        seen = None
        for name, p, g in todo:
            group = gmap.optimizers[name].param_groups[0]
            b1, b2 = group["betas"]
            state = self._row_state(name, p)
            state["step"] += 1
            state["row_step"][idx] += 1
            if name == "means":
                state["row_seen"][idx] += (g != 0).any(1).to(torch.float32)
                seen = state["row_seen"][idx]
            # exact per row (row_bias_correction), else torch's count of the tensor's steps (what the map-wide update
            # did: a row that is in view in few updates takes the larger, uncorrected first steps, which measured
            # better on short online schedules, README "Adam per Gaussian")
            if cfg.row_bias_correction:
                kd = state["row_step"][idx].double()
                a_rows = (-group["lr"] * (1.0 / (1.0 - b1 ** kd))).float()
                b_rows = torch.sqrt(1.0 - b2 ** kd).float()
            else:  # the tensor's count, read on the host (a CPU scalar): no round trip to the device per parameter
                k, f32 = float(state["step"]), dict(dtype=torch.float32, device=p.device)
                a_rows = torch.full((len(idx),), -group["lr"] * (1.0 / (1.0 - b1 ** k)), **f32)
                b_rows = torch.full((len(idx),), math.sqrt(1.0 - b2 ** k), **f32)
            if seen is not None:
                if name == "means" and cfg.means_decay_to != 1.0:
                    decay = torch.clamp(seen / cfg.means_decay_updates, max=1.0)
                    a_rows = a_rows * torch.pow(cfg.means_decay_to, decay)
                if cfg.warmup_updates > 0:
                    a_rows = a_rows * torch.clamp(seen / cfg.warmup_updates, max=1.0)
            shape = (a_rows.shape[0],) + (1,) * (p.ndim - 1)
            m, v, w, eps = state["exp_avg"], state["exp_avg_sq"], 1.0 - b1, group["eps"]
            mi = m[idx] + w * (g - m[idx])
            vi = v[idx] * b2 + (1.0 - b2) * g * g
            m[idx], v[idx] = mi, vi
            p.data[idx] = p.data[idx] + a_rows.view(shape) * (mi / (torch.sqrt(vi) / b_rows.view(shape) + eps))
