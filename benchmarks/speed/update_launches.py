"""Kernel launches, host synchronisations and host-device copies of one mapping update, by phase, without a GPU.

    python benchmarks/speed/update_launches.py                 # the fused (CUDA) path and the numba CPU path
    python benchmarks/speed/update_launches.py --kernels fused --floor 200
    python benchmarks/speed/update_launches.py --kernels numba --renderer cpu --ops   # the CPU path as it runs

A Reconstructor on the embedded synthetic room at 1/4 scale (area supervision) runs the kernel set chosen
(``--kernels``) with the gsplat backend on the CPU (its CUDA ops replaced by the stand-in of
``tests/helpers/gsplat_standin.py``), so the update takes the code path a CUDA map takes. Over ``--updates``
updates between MCMC relocation rounds every torch operator is seen by a ``TorchDispatchMode`` and every transfer
API call (``.cpu()``, ``.numpy()``, ``.item()``, ``torch.tensor``, ``bool(t)``, ...) by a ``TorchFunctionMode``;
each is attributed to the phase it ran in (the update's objects' public methods: the kernel set's ``select`` /
``backward`` / ``step``, the renderer, the growth policy's ``post_step``, the views' ``feedback``, ...). Counting
rules for a CUDA map:

- a launch: a compute operator on tensors (views, ``detach``, empty allocations: none), or a Triton launch of
  :mod:`eligsir_o3d.kernels.triton_launch`; gsplat's own are modelled: :data:`GSPLAT_FWD` + :data:`GSPLAT_BWD`
  launches and one synchronisation (its tile-intersection count), its stand-in's operators are not counted;
- a synchronisation: ``_local_scalar_dense``, ``nonzero``, ``unique``, ``masked_select``, boolean indexing;
- a copy: a transfer call inside a device phase (the asynchronous 8-byte copy of the fused view's row count is
  reported apart).

``--floor N`` also times N updates at 16x12 pixels and a few dozen Gaussians (the host's floor: what an update
costs when the kernels cost nothing), per kernel set, interleaved. ``count_update`` is what
``tests/kernels/test_launch_budget.py`` pins.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

from eligsir_o3d.kernels.triton_launch import in_launch

ROOT = Path(__file__).resolve().parents[2]
GSPLAT_FWD = 13  # projection, tile intersection (3), sort (3), offsets, SH, rasterisation, allocations' fills
GSPLAT_BWD = 9
DEVICE_PHASES = ("select", "render", "backward", "step", "mcmc", "feedback")
SYNC_OPS = {"_local_scalar_dense", "nonzero", "unique", "_unique2", "unique_dim", "masked_select", "bincount",
            "item", "is_nonzero", "equal"}
FREE_OPS = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided", "detach", "alias",
            "lift_fresh", "_unsafe_view", "set_", "resize_", "_reshape_alias", "unsqueeze_", "squeeze_"}
TRANSFERS = {"cpu", "numpy", "item", "tolist", "__bool__", "__int__", "__float__", "__index__", "tensor",
             "as_tensor", "from_numpy", "pin_memory"}


class Counts:
    """Per phase: launches, syncs, transfers and the operators' names (for the report)."""

    def __init__(self):
        self.phase = ["host"]
        self.paused = 0
        self.launches, self.syncs, self.copies = Counter(), Counter(), Counter()
        self.ops: dict[str, Counter] = defaultdict(Counter)

    @contextlib.contextmanager
    def within(self, name: str):
        self.phase.append(name)
        try:
            yield
        finally:
            self.phase.pop()

    @contextlib.contextmanager
    def pause(self):
        self.paused += 1
        try:
            yield
        finally:
            self.paused -= 1

    def per_update(self, n: int) -> dict:
        phases = sorted(set(self.launches) | set(self.syncs) | set(self.copies))
        return {"launches": sum(self.launches.values()) / n, "syncs": sum(self.syncs.values()) / n,
                "copies": sum(self.copies.values()) / n,
                "by_phase": {p: {"launches": self.launches[p] / n, "syncs": self.syncs[p] / n,
                                 "copies": self.copies[p] / n} for p in phases}}


class _Dispatch(TorchDispatchMode):
    def __init__(self, counts: Counts):
        super().__init__()
        self.c = counts

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        c = self.c
        if not c.paused and not in_launch():
            name = func.overloadpacket.__name__
            phase = c.phase[-1]
            c.ops[phase][name] += 1
            if name in SYNC_OPS or (name in ("index", "index_put_", "index_put") and _bool_index(args)):
                c.syncs[phase] += 1
            elif not (func.is_view or name in FREE_OPS):
                c.launches[phase] += 1
        return func(*args, **kwargs)


def _bool_index(args) -> bool:
    idx = args[1] if len(args) > 1 else None
    return isinstance(idx, (list, tuple)) and any(isinstance(t, torch.Tensor) and t.dtype == torch.bool for t in idx)


class _Functions(TorchFunctionMode):
    def __init__(self, counts: Counts):
        super().__init__()
        self.c = counts

    def __torch_function__(self, func, types, args=(), kwargs=None):
        c = self.c
        name = getattr(func, "__name__", "")
        made = name in ("tensor", "as_tensor") and args and isinstance(args[0], torch.Tensor)  # no data moves
        if not c.paused and not in_launch() and c.phase[-1] in DEVICE_PHASES and name in TRANSFERS and not made:
            c.copies[c.phase[-1]] += 1
        return func(*args, **(kwargs or {}))


def _opaque_gsplat(counts: Counts, rasterization):
    """gsplat's ``rasterization`` (the stand-in) as one opaque step: its operators are not counted, its launches
    are modelled (forward, backward and its one synchronisation)."""
    class Raster(torch.autograd.Function):
        @staticmethod
        def forward(ctx, means, quats, scales, opacities, colors, viewmats, Ks, width, height, kw):
            with counts.pause(), torch.enable_grad():
                ins = [t.detach().requires_grad_(t.requires_grad) for t in (means, quats, scales, opacities, colors)]
                rendered, alphas, meta = rasterization(*ins, viewmats, Ks, width, height, **kw)
            ctx.ins, ctx.outs = ins, (rendered, alphas)
            ctx.meta = meta
            return rendered.detach(), alphas.detach()

        @staticmethod
        def backward(ctx, g_rendered, g_alphas):
            counts.launches[counts.phase[-1]] += GSPLAT_BWD
            with counts.pause():
                need = [t for t in ctx.ins if t.requires_grad]
                grads = iter(torch.autograd.grad(ctx.outs, need, (g_rendered, g_alphas), allow_unused=True))
                out = [next(grads) if t.requires_grad else None for t in ctx.ins]
            return (*out, None, None, None, None, None)

    def raster(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        counts.launches[counts.phase[-1]] += GSPLAT_FWD
        counts.syncs[counts.phase[-1]] += 1
        box = {}
        rendered, alphas = Raster.apply(means, quats, scales, opacities, colors, viewmats, Ks, width, height, kw)
        return rendered, alphas, _LazyMeta(box)

    return raster


class _LazyMeta(dict):
    """gsplat's ``meta`` stands in empty: an update reads none of it (radii and means2d are made on demand)."""


def _wrap_phase(counts: Counts, obj, attr: str, phase: str) -> None:
    fn = getattr(obj, attr)

    def timed(*a, **kw):
        with counts.within(phase):
            return fn(*a, **kw)

    setattr(obj, attr, timed)


def build(kernels: str, frames: int = 12, size: tuple[int, int] | None = None, renderer: str = "gsplat"):
    """A warm Reconstructor of the embedded room with ``kernels`` and the gsplat backend on the stand-in (or, with
    ``renderer="cpu"``, the CPU path's own renderer), and its Counts (phases wired, counting idle)."""
    import pytest

    import eligsir_o3d as eo3d
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.render.gsplat_backend import GsplatRenderer

    import importlib.util

    spec = importlib.util.spec_from_file_location("gsplat_standin", ROOT / "tests" / "helpers" / "gsplat_standin.py")
    gsplat_standin = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gsplat_standin)

    mp = pytest.MonkeyPatch()
    rasterization = gsplat_standin.patch(mp)
    counts = Counts()
    seq = open_sequence("synthetic", n_frames=frames, **({} if size is None else {"width": size[0], "height": size[1]}))
    cfg = eo3d.Config(seed=0, renderer="torch")
    cfg.optim.kernels = kernels
    cfg.supervision.mode = "area"
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 10 ** 6, 10 ** 6  # no relocation round counted
    if renderer == "cpu":
        cfg.renderer = "cpu"
    rec = eo3d.Reconstructor(seq.camera, "cpu", cfg)
    if renderer != "cpu":
        rec.renderer = GsplatRenderer("cpu", rasterization=_opaque_gsplat(counts, rasterization))
    for i in range(len(seq)):
        rec.integrate(seq.frame(i), updates=4)
    for obj, attr, phase in ((rec.kernels, "select", "select"), (rec.renderer, "render", "render"),
                             (rec.kernels, "backward", "backward"), (rec.kernels, "step", "step"),
                             (rec.growth, "post_step", "mcmc"), (rec.views, "feedback", "feedback"),
                             (rec.views, "select", "choose view"), (rec.supervision, "sample", "sample")):
        _wrap_phase(counts, obj, attr, phase)
    return rec, counts, mp


def count_update(kernels: str = "fused", updates: int = 10, frames: int = 12, renderer: str = "gsplat") -> dict:
    """Launches, syncs and copies per update of ``kernels`` on the CUDA code path (see the module docstring); with
    ``renderer="cpu"`` the CPU path as a CPU run takes it (the cpu renderer's own operators counted)."""
    from eligsir_o3d.kernels import triton_launch

    rec, counts, mp = build(kernels, frames, renderer=renderer)
    try:
        rec.optimize(2)  # the views' first renders at this scale, caches
        counts.launches.clear(), counts.syncs.clear(), counts.copies.clear(), counts.ops.clear()
        n0 = triton_launch.launch_count()
        with _Functions(counts), _Dispatch(counts):
            rec.optimize(updates)
        counts.launches["triton"] += triton_launch.launch_count() - n0
    finally:
        mp.undo()
    out = counts.per_update(updates)
    out["kernels"], out["renderer"] = kernels, renderer
    out["gaussians"], out["in_view"] = len(rec.gmap), rec.last_in_view
    out["ops"] = {p: dict(c.most_common(12)) for p, c in counts.ops.items()}
    return out


def host_floor(kernels: list[str], updates: int, rounds: int = 3) -> dict:
    """Median ms per update at 16x12 pixels (a few dozen Gaussians) per kernel set, the sets interleaved."""
    recs = {}
    for k in kernels:
        rec, _, mp = build(k, frames=3, size=(64, 48))
        rec.config.supervision.mode = "area"
        recs[k] = (rec, mp)
    times = {k: [] for k in kernels}
    try:
        for _ in range(rounds):
            for k, (rec, _) in recs.items():
                rec.optimize(3)
                t0 = time.perf_counter()
                rec.optimize(updates, scale=0.25)
                times[k].append(1e3 * (time.perf_counter() - t0) / updates)
    finally:
        for _, mp in recs.values():
            mp.undo()
    return {k: sorted(v)[len(v) // 2] for k, v in times.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kernels", nargs="+", default=["fused", "torch", "numba"])
    ap.add_argument("--updates", type=int, default=10)
    ap.add_argument("--floor", type=int, default=0, help="also time this many updates at 16x12 per kernel set")
    ap.add_argument("--ops", action="store_true", help="print the most frequent operators per phase")
    ap.add_argument("--renderer", choices=("gsplat", "cpu"), default="gsplat",
                    help="gsplat: its CPU stand-in, the CUDA code path (default); cpu: the CPU path's own renderer")
    args = ap.parse_args(argv)
    for k in args.kernels:
        r = count_update(k, args.updates, renderer=args.renderer)
        ops = r.pop("ops")
        print(json.dumps(r))
        if args.ops:
            print(json.dumps(ops))
    if args.floor:
        print(json.dumps({"host_floor_ms": host_floor(args.kernels, args.floor)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
