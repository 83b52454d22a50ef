"""The ``numba`` kernel set: float32 maps on the CPU, each stage one or a few compiled passes.

- select: the view test over the raw means and log scales (:func:`..render.culling.map_in_view`: one pass, or the
  spatial index of a large map) and one pass gathering every parameter's rows as raw leaves;
- backward: the fused supervision loss of a ``cpu`` render (:class:`..optim.losses._FusedLossCPU`: value, error map
  and gradient into the compositing's accumulations), the regulariser through autograd;
- step: Adam over the view's rows of every parameter in one pass (:func:`.cpu_kernels.adam_rows`), then the
  position noise on those rows where they lie (:func:`..optim.update_kernels.mcmc_noise_rows`).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D, PARAM_NAMES
from ..render.culling import gather_rows as gather_raw
from .base import KernelSet, RowView, StepTerms, adam_factors, moments


def regulariser(view: RowView, terms: StepTerms) -> torch.Tensor | None:
    """``(opacity_reg * sum(opacity) + scale_reg * sum(scale) / 3) / N`` over the view's raw leaves: the gradient the
    map-wide means give the rows in view (the rows out of view held constant)."""
    if view.n_map == 0 or len(view) == 0 or (terms.opacity_reg <= 0 and terms.scale_reg <= 0):
        return None
    lv = view.leaves
    return (terms.opacity_reg * torch.sigmoid(lv["opacities"]).sum()
            + terms.scale_reg * torch.exp(lv["scales"]).sum() / 3.0) / view.n_map


class NumbaKernels(KernelSet):
    """Compiled CPU stages for float32 maps (see the module docstring)."""

    name = "numba"

    def select(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D, *, cull: bool = True,
               grad: bool = True, capacity: int = 0) -> RowView:
        from ..render.culling import map_in_view

        idx = map_in_view(gmap, camera, T_world_cam, low_pass) if cull else torch.arange(len(gmap))
        return RowView(gmap, idx, gather_raw(gmap, idx, grad), activated=False)

    def backward(self, out, color, depth, loss_cfg, view: RowView, terms: StepTerms) -> torch.Tensor:
        from ..optim.losses import supervision_loss

        loss, error = supervision_loss(out, color, depth, loss_cfg)
        if (reg := regulariser(view, terms)) is not None:
            loss = loss + reg
        if loss.requires_grad:  # an empty view (every row out of it) leaves nothing to differentiate
            loss.backward()
        return error

    def step(self, gmap, view: RowView, terms: StepTerms) -> None:
        from ..runtime.jit import rows_threads
        from .cpu_kernels import adam_rows

        if len(gmap) != view.n_map:
            raise RuntimeError(f"the map changed size ({view.n_map} -> {len(gmap)}) between render and step")
        ps, gs, ms, vs, hyper, widths = [], [], [], [], [], []
        for name in PARAM_NAMES:
            p, g = gmap.params[name], view.leaves[name].grad
            if g is None or p.numel() == 0:
                continue
            m, v = moments(gmap, name)
            ps.append(p.detach().view(-1).numpy())
            gs.append(g.contiguous().view(-1).numpy())
            ms.append(m.view(-1).numpy())
            vs.append(v.view(-1).numpy())
            hyper.append(adam_factors(gmap, name))
            widths.append(p.numel() // max(p.shape[0], 1))
        gmap.touched(view.idx)
        if ps:
            with rows_threads(len(view.idx)):
                adam_rows(tuple(ps), tuple(gs), tuple(ms), tuple(vs), np.array(hyper, np.float64),
                          np.array(widths, np.int64), view.idx.numpy())
        if terms.noise_scaler > 0:
            self.noise(gmap, view.idx, terms.noise_scaler, terms.generator)

    def noise(self, gmap, rows, scaler: float, generator) -> None:
        from ..scheduling.mcmc import inject_noise

        inject_noise(gmap, scaler, generator, rows)
