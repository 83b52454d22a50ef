"""The ``fused`` kernel set: the device path of an update, a few fused kernels and no host synchronisation of its own.

- select: the view test, the compaction of the rows in view into a row capacity, their gather and activations
  (:func:`.triton_select.select_rows`); the capacity is a power of two (at least 1024) above the last view's rows,
  so its shapes repeat; the number of rows in view stays on the device and reaches the host by an asynchronous
  8-byte copy that the renderer's own synchronisation completes. A view that held fewer rows than passed the test
  is selected again with room for all (``Reconstructor._draw_view``). Padding rows have opacity 0: renderers
  skip them and they get no gradient.
- backward: the fused loss from the render's accumulations (:func:`.triton_loss.fused_loss`: background, L1,
  'valid' D-SSIM, depth L1 over the valid pixels with the count on the device, the error map and the gradient),
  then autograd through the renderer only (``torch.autograd.backward`` from the accumulations); a render without
  accumulations takes the torch loss.
- step: chain rule of the activations, regulariser, Adam with torch's per-tensor bias correction as host scalars,
  and the position noise, one launch over the capacity (:func:`.triton_step.step_rows`), rows written in place.
- the views' feedback: the training render's error folded into their microcells on the device in two launches
  (:func:`.triton_feedback.fold_cells`).

With Triton importable the stages are its kernels (compiled on CUDA, interpreted on the CPU); without it the same
stages in torch operators (:mod:`.device_reference`), which is also their test oracle.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, PARAM_NAMES
from ..core.per_view import PerView
from .base import KernelSet, RowView, StepTerms, adam_scalars, moments
from .device_reference import AdamScalars

MIN_CAPACITY = 1024


def bucket(rows: int) -> int:
    """The row capacity for ``rows`` rows: the next power of two, at least :data:`MIN_CAPACITY`."""
    return max(MIN_CAPACITY, 1 << max(0, int(rows) - 1).bit_length())


def stages(use_triton: bool | None = None):
    """The functions (select, loss, step, feedback fold) that implement the stages: Triton's where it imports (or
    as asked); without it the torch references, whose fold is the microcells' own (None)."""
    from . import triton_launch

    if use_triton is None:
        use_triton = triton_launch.available()
    if use_triton:
        from . import triton_loss, triton_select, triton_step

        from .triton_feedback import fold_cells

        return triton_select.select_rows, triton_loss.fused_loss, triton_step.step_rows, fold_cells
    from . import device_reference, device_reference_loss

    return device_reference.select_rows, device_reference_loss.fused_loss, device_reference.step_rows, None


def view_args(camera: Camera, T_world_cam, low_pass: float) -> tuple[tuple, tuple]:
    """(V, cam) as host scalars: the world-to-camera rows (12 floats) and the view test's camera bounds (9)."""
    from ..render.culling import camera_bounds, view_matrix

    R, t = view_matrix(T_world_cam)
    V = tuple(float(x) for x in np.concatenate([R, t[:, None]], 1).ravel())
    return V, tuple(float(c) for c in camera_bounds(camera, low_pass))


class FusedKernels(KernelSet):
    """The device path (see the module docstring) for a map on ``device``."""

    name = "fused"

    def __init__(self, device: str | torch.device = "cpu", use_triton: bool | None = None):
        self.device = torch.device(device)
        self._select, self._loss, self._step, self.fold_cells = stages(use_triton)
        self.capacity = MIN_CAPACITY  # rows of the next view: grows with the views, shrinks when 4x too large
        self.view_args = PerView(view_args)  # the view test's host scalars of the views seen recently

    def _count_host(self, count: torch.Tensor) -> np.ndarray:
        """The host's view of ``count`` [1]: on a GPU a pinned buffer filled asynchronously, on the CPU the tensor."""
        if count.device.type == "cpu":
            return count.numpy()
        host = torch.empty(1, dtype=count.dtype, pin_memory=True)
        host.copy_(count, non_blocking=True)
        return host.numpy()

    def select(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D, *, cull: bool = True,
               grad: bool = True, capacity: int = 0) -> RowView:
        if not cull:  # every row: the torch set's gather and the fused step over all of them
            return self._all_rows(gmap, grad)
        if capacity:
            self.capacity = bucket(capacity)
        p = gmap.params
        V, cam = self.view_args(camera, T_world_cam, float(low_pass))
        sel = self._select(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"], p["shN"], V, cam,
                           self.capacity, gmap.sh_degree)
        leaves = {"means": sel.means, "quats": sel.quats, "scales": sel.scales, "opacities": sel.opacities,
                  "colors": sel.colors}
        for t in leaves.values():
            t.requires_grad_(grad)
        view = RowView(gmap, sel.idx, leaves, activated=True, count=sel.count, count_host=self._count_host(sel.count))
        return view

    def _all_rows(self, gmap, grad: bool) -> RowView:
        n, dev = len(gmap), gmap.device
        idx = torch.arange(n, device=dev)
        leaves = {n_: t.detach().clone().requires_grad_(grad) for n_, t in
                  zip(("means", "quats", "scales", "opacities", "colors"), gmap.render_args())}
        return RowView(gmap, idx, leaves, activated=True, count=torch.full((1,), n, device=dev),
                       count_host=np.array([n], np.int64))

    def backward(self, out, color, depth, loss_cfg, view: RowView, terms: StepTerms) -> torch.Tensor:
        c = loss_cfg
        if out.raw is None:
            from ..optim.losses import torch_loss

            loss, error = torch_loss(out, color, depth, c)
            if loss.requires_grad:
                loss.backward()
            return error
        acc, alpha, background = out.raw
        loss, error, g_acc, g_alpha = self._loss(acc, alpha, background, color, depth, c.lambda_dssim,
                                                 c.lambda_depth, c.depth_alpha_min)
        if acc.requires_grad:
            torch.autograd.backward([acc, alpha], [g_acc, g_alpha])
        self.last_loss = loss  # a device scalar, for whoever wants to read it
        return error

    def step(self, gmap, view: RowView, terms: StepTerms) -> None:
        if len(gmap) != view.n_map:
            raise RuntimeError(f"the map changed size ({view.n_map} -> {len(gmap)}) between render and step")
        self.capacity = max(MIN_CAPACITY, bucket(len(view))) if len(view) * 4 < self.capacity else self.capacity
        grads = {n: t.grad for n, t in view.leaves.items()}
        stepped = [n for n, g in (("means", grads["means"]), ("quats", grads["quats"]), ("scales", grads["scales"]),
                                  ("opacities", grads["opacities"]), ("sh0", grads["colors"]),
                                  ("shN", grads["colors"])) if g is not None and gmap.params[n].numel() > 0]
        adam = {}
        for n in stepped:
            a, b, b1, b2, eps = adam_scalars(gmap, n)
            adam[n] = AdamScalars(b1, b2, eps, a, b)
        exp_avg, exp_avg_sq = {}, {}
        for n in PARAM_NAMES:
            exp_avg[n], exp_avg_sq[n] = moments(gmap, n)
        z = None
        if terms.noise_scaler > 0:
            z = torch.randn(view.capacity, 3, generator=terms.generator, device=gmap.device)
        self._step(gmap.params, exp_avg, exp_avg_sq, view.idx, view.count, grads, adam, terms.opacity_reg,
                   terms.scale_reg, max(view.n_map, 1), terms.noise_scaler, z)
        gmap.touched(view.idx)

    def noise(self, gmap, rows, scaler: float, generator) -> None:
        from .reference import noise_torch

        noise_torch(gmap, rows, scaler, generator)

    def count_in_view(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D) -> int:
        from .device_reference import view_hits

        V, cam = view_args(camera, T_world_cam, low_pass)
        return int(view_hits(gmap.params["means"], gmap.params["scales"], V, cam).sum())
