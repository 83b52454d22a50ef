"""The ``numba`` kernel set: float32 maps on the CPU, each stage one or a few compiled passes.

- select: the view test over the raw means and log scales (:func:`..render.culling.map_in_view`: one pass, or the
  spatial index of a large map) and one pass gathering the rows activated, as the renderer takes them
  (:func:`.cpu_kernels.gather_activated`);
- draw: the ``cpu`` renderer's training pass for RGB rows (:meth:`..render.cpu_backend.CpuRenderer.render_training`:
  the compiled passes without an autograd graph), other renders through autograd;
- backward: the fused supervision loss of a ``cpu`` render (:func:`..optim.losses.fused_loss_cpu`: error map and
  gradient with respect to the compositing's accumulations), handed to the training pass's backward, which sets
  the leaves' gradients (or to autograd's); other renders take the torch loss;
- step: one pass over the view's rows (:func:`.cpu_kernels.step_view`): the activations' chain rule, the
  regulariser's gradient, Adam on every parameter and the position noise, in place on the map's rows;
- the views' feedback: the error map folded into the microcells in one pass (:func:`.cpu_feedback.fold_samples`).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.camera import Camera
from ..core.gaussians import EPS2D
from ..optim.losses import fused_applies, fused_loss_cpu, torch_loss
from ..render import culling
from ..render.culling import gather_rows as gather_raw
from .base import KernelSet, RowView, StepTerms, adam_factors

_compiled = []  # [cpu_kernels, runtime.jit] once loaded: numba is imported on the first update, not with the module


def compiled():
    """(:mod:`.cpu_kernels`, :mod:`..runtime.jit`), imported on first use."""
    if not _compiled:
        from ..runtime import jit
        from . import cpu_kernels

        _compiled.extend((cpu_kernels, jit))
    return _compiled


def regulariser(view: RowView, terms: StepTerms) -> torch.Tensor | None:
    """``(opacity_reg * sum(opacity) + scale_reg * sum(scale) / 3) / N`` over the view's raw leaves: the gradient the
    map-wide means give the rows in view (the rows out of view held constant)."""
    if view.n_map == 0 or len(view) == 0 or (terms.opacity_reg <= 0 and terms.scale_reg <= 0):
        return None
    lv = view.leaves
    return (terms.opacity_reg * torch.sigmoid(lv["opacities"]).sum()
            + terms.scale_reg * torch.exp(lv["scales"]).sum() / 3.0) / view.n_map


def fold_cells(plan, error_map: torch.Tensor, error: torch.Tensor, best: torch.Tensor, visits: torch.Tensor,
               ema: float) -> None:
    """:func:`..scheduling.cell_feedback.fold_torch` (same arguments) in one compiled pass
    (:func:`.cpu_feedback.fold_samples`) where the map's statistics are float32 and int64 on the CPU."""
    if error.dtype != torch.float32 or best.dtype != torch.float32 or visits.dtype != torch.int64 or \
            error_map.dtype != torch.float32 or error_map.device.type != "cpu":
        from ..scheduling.cell_feedback import fold_torch

        fold_torch(plan, error_map, error, best, visits, ema)
        return
    from .cpu_feedback import fold_samples

    host = plan.__dict__.get("host")  # the plan's tensors as numpy arrays, made once per plan
    if host is None:
        host = plan.host = tuple(t.numpy() for t in (plan.pix, plan.inv, plan.cells, plan.counts, plan.scratch))
    fold_samples(error_map.contiguous().numpy(), *host, float(ema), error.numpy(), best.numpy(), visits.numpy(),
                 plan.last.numpy())


class NumbaKernels(KernelSet):
    """Compiled CPU stages for float32 maps (see the module docstring)."""

    name = "numba"
    fold_cells = staticmethod(fold_cells)

    def select(self, gmap, camera: Camera, T_world_cam, low_pass: float = EPS2D, *, cull: bool = True,
               grad: bool = True, capacity: int = 0) -> RowView:
        idx = culling.map_in_view(gmap, camera, T_world_cam, low_pass) if cull else torch.arange(len(gmap))
        return RowView(gmap, idx, gather_activated_rows(gmap, idx, grad), activated=True)

    def draw(self, renderer, view: RowView, camera: Camera, T_world_cam, background=None, low_pass: float = EPS2D):
        """The ``cpu`` renderer's training pass (:meth:`..render.cpu_backend.CpuRenderer.render_training`: no
        autograd graph; :meth:`backward` sets the leaves' gradients) where the view's colours are RGB; otherwise
        the renderer's render through autograd."""
        render_training = getattr(renderer, "render_training", None)
        if render_training is None or not view.activated or view.leaves["colors"].dim() != 2:
            return super().draw(renderer, view, camera, T_world_cam, background, low_pass)
        return render_training(*view.render_args(), camera, T_world_cam, background, low_pass=low_pass)

    def backward(self, out, color, depth, loss_cfg, view: RowView, terms: StepTerms) -> torch.Tensor:
        training_pass = getattr(out, "training_pass", None)
        if training_pass is None and not fused_applies(out, color):
            loss, error = torch_loss(out, color, depth, loss_cfg)
            if loss.requires_grad:
                loss.backward()
            return error
        acc, alpha, background = out.raw
        _, error, g_acc, g_alpha = fused_loss_cpu(acc, alpha, background, color, depth, loss_cfg)
        # an empty view (every row out of it) leaves nothing to differentiate
        if training_pass is not None and len(view):
            grads = training_pass.backward(g_acc, g_alpha)
            for name, g in zip(("means", "quats", "scales", "opacities", "colors"), grads):
                view.leaves[name].grad = g
        elif training_pass is None and acc.requires_grad:
            torch.autograd.backward((acc, alpha), (g_acc, g_alpha))
        return error

    def step(self, gmap, view: RowView, terms: StepTerms) -> None:
        if len(gmap) != view.n_map:
            raise RuntimeError(f"the map changed size ({view.n_map} -> {len(gmap)}) between render and step")
        step_activated(gmap, view, terms)

    def noise(self, gmap, rows, scaler: float, generator) -> None:
        from ..scheduling.mcmc import inject_noise

        inject_noise(gmap, scaler, generator, rows)


def gather_activated_rows(gmap, idx: torch.Tensor, grad: bool) -> dict:
    """The rows ``idx`` of a float32 CPU map, activated as :meth:`RowView.render_args` activates raw leaves, as
    new leaf tensors (requiring grad with ``grad``) by name: means, quats, scales, opacities, colors."""
    k_, jit = compiled()
    m, deg0, k = idx.numel(), gmap.sh_degree == 0, (gmap.sh_degree + 1) ** 2 - 1
    out = {"means": torch.empty(m, 3), "quats": torch.empty(m, 4), "scales": torch.empty(m, 3),
           "opacities": torch.empty(m), "colors": torch.empty(m, 3) if deg0 else torch.empty(m, 1 + k, 3)}
    with jit.rows_threads(m, "gather_activated"):
        k_.gather_activated(host_params(gmap), idx.numpy(), deg0, out["means"].numpy(), out["quats"].numpy(),
                         out["scales"].numpy(), out["opacities"].numpy(),
                         out["colors"].view(m, 3 if deg0 else 3 + 3 * k).numpy())
    if grad:
        for t in out.values():
            t.requires_grad_(True)
    return out


_STEPPED = ("means", "quats", "scales", "opacities", "sh0", "shN")  # :func:`.cpu_kernels.step_view`'s order


def host_params(gmap, which: int = 0) -> tuple:
    """The map's flat host arrays (:meth:`GaussianMap.host_buffers`) in the kernels' order: ``which`` 0 the
    parameters, 1 exp_avg, 2 exp_avg_sq."""
    bufs = gmap.host_buffers()
    return tuple(bufs[n][which] for n in _STEPPED)


_EMPTY = {1: np.zeros(0, np.float32), 2: np.zeros((0, 0), np.float32)}  # a gradient not given


def _host(grad: torch.Tensor | None, ndim: int, rows: int) -> np.ndarray:
    """A leaf's gradient as the kernel reads it ([M] or [M, width], any strides), or an empty stand-in."""
    if grad is None or grad.numel() == 0:
        return _EMPTY[ndim]
    return (grad if ndim == 1 or grad.ndim == 2 else grad.reshape(rows, -1)).numpy()


def step_activated(gmap, view: RowView, terms: StepTerms) -> None:
    """:func:`.cpu_kernels.step_view` on ``view``'s rows from its leaves' gradients: the chain rule (activated
    leaves; raw leaves carry the raw parameters' gradients), the regulariser (``terms``' weights over the map's
    mean), Adam (one step counted for each parameter with a gradient and rows) and, where ``terms.noise_scaler``
    > 0, the position noise (one normal triple per row drawn from ``terms.generator``)."""
    k_, jit = compiled()
    idx, lv, m = view.idx, view.leaves, view.idx.numel()
    if view.activated:
        gc = lv["colors"].grad
        grads = [lv[n].grad for n in ("means", "quats", "scales", "opacities")] + [gc, gc]
    else:
        grads = [lv[n].grad for n in _STEPPED]
    has = np.zeros(6, np.bool_)
    hyper = np.zeros((6, k_.HYPER), np.float64)
    for t, (name, g) in enumerate(zip(_STEPPED, grads)):
        if g is not None and len(gmap) > 0 and (name != "shN" or gmap.sh_degree > 0):
            has[t] = True
            hyper[t] = adam_factors(gmap, name)
    gmap.touched(idx)
    noise = terms.noise_scaler > 0
    z = torch.randn(m, 3, generator=terms.generator).numpy() if noise and m else _EMPTY[2]
    if m == 0 or not (has.any() or noise):
        return
    host = [_host(g, 1 if t == k_.OPACITIES else 2, m) for t, g in enumerate(grads)]
    if view.activated and gmap.sh_degree > 0 and grads[4] is not None:  # [M, (K + 1) 3]: DC, then the rest
        host[4], host[5] = host[4][:, :3], host[4][:, 3:]
    n_map = max(view.n_map, 1)
    with jit.rows_threads(m, "step_view"):
        k_.step_view(host_params(gmap), host_params(gmap, 1), host_params(gmap, 2), *host, has, hyper, idx.numpy(),
                     gmap.sh_degree == 0, view.activated, terms.opacity_reg / n_map,
                     terms.scale_reg / (3.0 * n_map), z, terms.noise_scaler if noise else 0.0)
