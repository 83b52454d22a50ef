"""The map's Adam: its state as plain tensors beside the parameters, and the map-wide step.

:class:`MapAdam` is ``torch.optim.Adam`` (no weight decay, no AMSGrad) over the map's parameter tensors, with the
state held where the map can resize it with the parameters instead of in one optimizer per tensor: per parameter
name the moments ``exp_avg`` and ``exp_avg_sq`` ([N, ...], the parameter's shape; the map keeps them as views of
its capacity buffers), the step count (a host int, counted per tensor as torch counts it) and the learning rate
(mutable: a schedule may change it between updates). A step, map-wide (:meth:`MapAdam.step_map`) or on the rows
in view, takes its step sizes from :meth:`MapAdam.bias`, so every path counts the steps alike:

    a, b = adam.bias(name)          # k += 1; a = -lr / (1 - beta1^k), b = sqrt(1 - beta2^k)
    m += (1 - beta1) (g - m);  v = v beta2 + (1 - beta2) g^2;  p += a m / (sqrt(v) / b + eps)

On float32 CPU tensors the step is one compiled pass over every parameter (:mod:`.adam_kernels`), elsewhere
torch's own operators in torch's order; both agree with ``torch.optim.Adam`` to float32 rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class AdamConfig:
    """Adam's decay rates of the two moments and the denominator's epsilon (torch's Adam, one step count per
    parameter tensor)."""

    beta1: float = 0.9
    """Decay rate of the first moment (the gradient's running mean)."""
    beta2: float = 0.999
    """Decay rate of the second moment (the squared gradient's running mean)."""
    eps: float = 1e-15
    """Added to the second moment's square root in the step's denominator."""


class MapAdam:
    """Adam's state of a map's parameters, by name: ``exp_avg[name]``, ``exp_avg_sq[name]`` (tensors shaped like
    the parameter), ``steps[name]`` (int), ``lr[name]`` (float), and ``beta1``, ``beta2``, ``eps``.

    The owner (:class:`.core.gaussians.GaussianMap`) sets the moment tensors and keeps them aligned with its rows;
    a row whose moments are zero starts as a fresh parameter would (its bias correction is the tensor's count).
    """

    def __init__(self, lr: dict[str, float], config: AdamConfig | None = None):
        config = config or AdamConfig()
        if not (0 <= config.beta1 < 1 and 0 <= config.beta2 < 1 and config.eps > 0):
            raise ValueError(f"optim.adam: betas must lie in [0, 1) and eps > 0, got beta1={config.beta1}, "
                             f"beta2={config.beta2}, eps={config.eps}")
        self.beta1, self.beta2, self.eps = float(config.beta1), float(config.beta2), float(config.eps)
        self.lr = {n: float(v) for n, v in lr.items()}
        self.steps = {n: 0 for n in lr}
        self.exp_avg: dict[str, torch.Tensor] = {}
        self.exp_avg_sq: dict[str, torch.Tensor] = {}

    def bias(self, name: str) -> tuple[float, float]:
        """Count one step of ``name`` and return its step factors (host floats): a = -lr / (1 - beta1^k) and
        b = sqrt(1 - beta2^k), k the new count."""
        self.steps[name] += 1
        k = self.steps[name]
        return -self.lr[name] / (1.0 - self.beta1 ** k), (1.0 - self.beta2 ** k) ** 0.5

    @torch.no_grad()
    def step_map(self, params: dict, grads: dict) -> None:
        """One Adam step, in place, of every parameter ``params[name]`` whose ``grads[name]`` is not None (every
        row; parameters without rows are skipped and keep their count)."""
        todo = [(n, params[n], grads.get(n)) for n in params]
        todo = [(n, p, g) for n, p, g in todo if g is not None and p.numel() > 0]
        if not todo:
            return
        compiled = all(p.device.type == "cpu" and p.dtype == g.dtype == torch.float32 and p.is_contiguous()
                       for _, p, g in todo)
        w, b2, w2, eps = 1.0 - self.beta1, self.beta2, 1.0 - self.beta2, self.eps
        if compiled:
            import numpy as np

            from .adam_kernels import adam_tensors

            flat = lambda t: t.detach().contiguous().view(-1).numpy()  # noqa: E731
            hyper = np.array([(w, b2, w2, eps) + self.bias(n) for n, _, _ in todo], np.float32)
            adam_tensors(tuple(p.detach().view(-1).numpy() for _, p, _ in todo), tuple(flat(g) for _, _, g in todo),
                         tuple(self.exp_avg[n].view(-1).numpy() for n, _, _ in todo),
                         tuple(self.exp_avg_sq[n].view(-1).numpy() for n, _, _ in todo), hyper)
            return
        for name, p, g in todo:  # torch's single-tensor Adam, operator for operator
            a, b = self.bias(name)
            m, v = self.exp_avg[name], self.exp_avg_sq[name]
            m.lerp_(g, w)
            v.mul_(b2).addcmul_(g, g, value=w2)
            p.addcdiv_(m, v.sqrt().div_(b).add_(eps), value=a)

    # ---- persistence -----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Plain values and CPU copies of the moments (the live ones change under the next step)."""
        copy = lambda d: {n: t.detach().cpu().clone() for n, t in d.items()}  # noqa: E731
        return {"beta1": self.beta1, "beta2": self.beta2, "eps": self.eps, "lr": dict(self.lr),
                "steps": dict(self.steps), "exp_avg": copy(self.exp_avg), "exp_avg_sq": copy(self.exp_avg_sq)}

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned; the moments are copied into the current moment tensors,
        which must have the stored shapes."""
        self.beta1, self.beta2, self.eps = float(state["beta1"]), float(state["beta2"]), float(state["eps"])
        self.lr.update({n: float(v) for n, v in state["lr"].items()})
        self.steps.update({n: int(v) for n, v in state["steps"].items()})
        for key in ("exp_avg", "exp_avg_sq"):
            live = getattr(self, key)
            for n, t in state[key].items():
                if tuple(t.shape) != tuple(live[n].shape):
                    raise ValueError(f"Adam state {key}[{n}] has shape {tuple(t.shape)}, the parameter "
                                     f"{tuple(live[n].shape)}")
                live[n].copy_(t)
