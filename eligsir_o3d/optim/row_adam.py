"""Adam with a per-Gaussian schedule (:class:`.gaussians.AdamConfig`): each row of a parameter (one Gaussian)
carries its own step count since its moments were zeroed (``row_step``) and, for the positions, the number of
updates whose gradient reached it (``row_seen``), both kept in the optimizer's state so that every insertion,
removal, relocation (:meth:`.gaussians.GaussianMap._resize`, ``assign``) and checkpoint carries them like the
moments. From them come a bias correction per row, the position step-size decay with a Gaussian's age and a
warm-up of new Gaussians. On a CPU map one compiled pass (:func:`._update_kernels.adam_rows_step`), elsewhere the
same formula in torch.
"""

from __future__ import annotations

import torch


def _row_factors(gmap, name: str, state: dict, lr: float, b1: float, b2: float, seen: torch.Tensor | None):
    """(a_rows, b_rows): -lr_r / bias correction 1 and sqrt(bias correction 2) of every row of ``name`` ([1]
    each when every row has the same)."""
    cfg = gmap.adam
    if cfg.row_bias_correction:
        k = state["row_step"].double()
        a_rows, b_rows = -lr / (1.0 - b1 ** k), torch.sqrt(1.0 - b2 ** k)
    else:
        step = float(state["step"])
        a_rows = torch.tensor([-lr / (1.0 - b1 ** step)], dtype=torch.float64, device=state["row_step"].device)
        b_rows = torch.tensor([(1.0 - b2 ** step) ** 0.5], dtype=torch.float64, device=state["row_step"].device)
    a_rows, b_rows = a_rows.float(), b_rows.float()
    if seen is not None:
        if name == "means" and cfg.means_decay_to != 1.0:
            a_rows = a_rows * torch.pow(cfg.means_decay_to, torch.clamp(seen / cfg.means_decay_updates, max=1.0))
        if cfg.warmup_updates > 0:
            a_rows = a_rows * torch.clamp(seen / cfg.warmup_updates, max=1.0)
    return a_rows, b_rows


def row_adam_step(gmap) -> None:
    """One Adam step over every parameter of ``gmap`` that received a gradient, with the rows' schedule."""
    from . import update_kernels as uk

    n = len(gmap)
    seen = None
    items = []
    for name in gmap.optimizers:  # "means" first: its row_seen is every row's age in updates seen
        p, opt = gmap.params[name], gmap.optimizers[name]
        if p.grad is None or p.numel() == 0:
            continue
        group = opt.param_groups[0]
        b1, b2 = group["betas"]
        state = uk.adam_state(opt, p)
        if "row_step" not in state:  # a state of torch's Adam (a checkpoint without rows): count from now
            state["row_step"] = torch.zeros(n, dtype=torch.float32, device=p.device)
        state["step"] += 1
        state["row_step"] += 1
        if name == "means":
            if "row_seen" not in state:
                state["row_seen"] = torch.zeros(n, dtype=torch.float32, device=p.device)
            state["row_seen"] += (p.grad.detach() != 0).any(1).to(torch.float32)
            seen = state["row_seen"]
        a_rows, b_rows = _row_factors(gmap, name, state, group["lr"], b1, b2, seen)
        items.append((p, p.grad, state["exp_avg"], state["exp_avg_sq"], a_rows, b_rows,
                      (1.0 - b1, b2, 1.0 - b2, group["eps"])))
    if gmap.device.type == "cpu" and all(it[0].dtype == torch.float32 for it in items):
        uk.adam_rows_step(items)
        return
    with torch.no_grad():
        for p, g, m, v, a_rows, b_rows, (w, beta2, w2, eps) in items:
            shape = (a_rows.shape[0],) + (1,) * (p.ndim - 1)
            m.add_(w * (g - m))
            v.mul_(beta2).add_(w2 * g * g)
            p.add_(a_rows.view(shape) * (m / (torch.sqrt(v) / b_rows.view(b_rows.shape[0], *shape[1:]) + eps)))
