"""Main's CPU update against the fused one, from one kitchen checkpoint: a difference of meaning or rounding?

    python benchmarks/quality/update_ab.py RUN/checkpoint.pt --one 3 --chain 200

Four kernel sets on the same restored map: ``A`` the numba set as main had it before the fused step (raw leaves,
torch's activations and the MCMC regulariser through autograd, Adam over the rows in one compiled pass, then the
position noise), ``A'`` the same with the regulariser's scalars grouped differently (a rounding-only change),
``B`` the checkout's numba set (activated gather, fused loss handed to the renderer's backward, chain rule +
regulariser + Adam + noise in one pass) and ``T`` that set with torch's activations (raw leaves activated by
autograd; the chain rule through the activations in autograd, the regulariser and Adam in the fused pass).

``--one K``: K single updates (different views), each from the checkpoint's map through A and B: per parameter
group the largest and median |A - B| of the rows in view beside the update's own size |A - map|, and the Adam
moments' relative differences. ``--chain K``: K updates in a row by each set's own Reconstructor (same seeds): how
far each set's means have moved from A's after 1, 2, 5, ... updates (median / 90th percentile / largest distance).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"


def kernel_sets():
    """{name: KernelSet class} of A, A', B and T (see the module docstring)."""
    from numba import prange

    from eligsir_o3d.core.gaussians import EPS2D, PARAM_NAMES
    from eligsir_o3d.kernels.base import RowView, adam_factors, moments
    from eligsir_o3d.kernels.cpu import NumbaKernels, regulariser
    from eligsir_o3d.optim.losses import supervision_loss
    from eligsir_o3d.render.culling import gather_rows, map_in_view
    from eligsir_o3d.runtime.jit import jit, rows_threads

    @jit
    def adam_rows(ps, gs, ms, vs, hyper, widths, rows):  # main's Adam pass, as it was
        for t in range(len(ps)):
            p, g, m, v, wd = ps[t], gs[t], ms[t], vs[t], widths[t]
            ar, br = np.float32(hyper[t, 0]), np.float32(hyper[t, 1])
            w, b2, w2, eps = (np.float32(hyper[t, 2]), np.float32(hyper[t, 3]), np.float32(hyper[t, 4]),
                              np.float32(hyper[t, 5]))
            for r in prange(rows.shape[0]):
                for j in range(wd):
                    i, gi = rows[r] * wd + j, g[r * wd + j]
                    mi = m[i] + w * (gi - m[i])
                    vi = v[i] * b2 + w2 * gi * gi
                    m[i], v[i] = mi, vi
                    p[i] = p[i] + ar * (mi / (np.sqrt(vi) / br + eps))

    def raw_select(self, gmap, camera, T, low_pass=EPS2D, *, cull=True, grad=True, capacity=0):
        idx = map_in_view(gmap, camera, T, low_pass) if cull else torch.arange(len(gmap))
        return RowView(gmap, idx, gather_rows(gmap, idx, grad), activated=False)

    def regrouped(view, terms):
        if view.n_map == 0 or len(view) == 0 or (terms.opacity_reg <= 0 and terms.scale_reg <= 0):
            return None
        lv = view.leaves
        return (terms.opacity_reg / view.n_map) * torch.sigmoid(lv["opacities"]).sum() \
            + (terms.scale_reg / (3.0 * view.n_map)) * torch.exp(lv["scales"]).sum()

    class A(NumbaKernels):
        reg = staticmethod(regulariser)
        select = raw_select

        def backward(self, out, color, depth, loss_cfg, view, terms):
            loss, error = supervision_loss(out, color, depth, loss_cfg)
            if (reg := self.reg(view, terms)) is not None:
                loss = loss + reg
            if loss.requires_grad:
                loss.backward()
            return error

        def step(self, gmap, view, terms):
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

    class A2(A):
        reg = staticmethod(regrouped)

    class T(NumbaKernels):
        select = raw_select

    return {"A": A, "A'": A2, "B": NumbaKernels, "T": T}


def restore(path: Path, seq, kernels):
    from eligsir_o3d import Reconstructor
    from eligsir_o3d.io.checkpoint import read_checkpoint

    rec = Reconstructor.from_checkpoint(read_checkpoint(path, sequence=seq), "cpu")
    rec.kernels = kernels()
    return rec


def one(rec, sets, trials: int) -> None:
    from eligsir_o3d.core.gaussians import PARAM_NAMES, GaussianMap
    from eligsir_o3d.kernels import StepTerms

    state = rec.gmap.state_dict()
    ctx = rec.context() if hasattr(rec, "context") else rec.ctx
    frames, rng = rec.views.views, torch.Generator().manual_seed(0)

    def clone():
        g = GaussianMap(rec.gmap.sh_degree, "cpu", rec.gmap.lrs, rec.gmap.adam_config)
        g.load_state_dict({**state, "params": {n: t.clone() for n, t in state["params"].items()}})
        g.supervision_focal = rec.gmap.supervision_focal
        return g

    def update(K, gm, frame, sample, seed):
        t = rec.growth.step_terms(ctx)
        terms = StepTerms(t.opacity_reg, t.scale_reg, t.noise_scaler, torch.Generator().manual_seed(seed))
        view = K.select(gm, sample.camera, frame.T_world_cam, sample.low_pass)
        out = rec.renderer.render(*view.render_args(), sample.camera, frame.T_world_cam, rec._background,
                                  low_pass=sample.low_pass)
        K.backward(out, sample.color, sample.depth, rec.config.optim.loss, view, terms)
        K.step(gm, view, terms)
        return view.idx

    for k in range(trials):
        frame = frames[(7 * k) % len(frames)]
        sample = rec.supervision.sample(frame, rec.fidelity.scale(), rng, "cpu")
        maps = clone(), clone(), clone()
        rows = update(sets["A"](), maps[0], frame, sample, k)
        assert torch.equal(rows, update(sets["B"](), maps[1], frame, sample, k))
        print(f"update {k}: view of frame {frame.index}, {rows.numel()} rows, {sample.camera.width}x"
              f"{sample.camera.height}")
        print("| group | max abs A - B | median | max abs A - map | median | m1 median rel | m1 mean signed rel |"
              " m2 median rel |\n|---|---|---|---|---|---|---|---|")
        for n in PARAM_NAMES:
            a, b, o = (m.params[n].detach()[rows].flatten() for m in maps)
            if a.numel() == 0:
                continue
            d, s = (a - b).abs(), (a - o).abs()
            rel = []
            for which in (maps[0].adam.exp_avg, maps[1].adam.exp_avg), (maps[0].adam.exp_avg_sq,
                                                                         maps[1].adam.exp_avg_sq):
                ma, mb = which[0][n][rows].flatten(), which[1][n][rows].flatten()
                rel.append((ma - mb) / (ma.abs() + 1e-30))
            print(f"| {n} | {d.max():.1e} | {d.median():.1e} | {s.max():.1e} | {s.median():.1e} | "
                  f"{rel[0].abs().median():.1e} | {rel[0].mean():+.1e} | {rel[1].abs().median():.1e} |")


def chain(path: Path, seq, sets, steps: int) -> None:
    recs = {name: restore(path, seq, K) for name, K in sets.items()}
    marks = {1, 2, 5, 10, 20, 50, 100, 200, 500, 1000}
    print("| updates | " + " | ".join(f"{n}: |means - A's| m, median / p90 / max" for n in ("A'", "B", "T")) +
          " |\n|---|---|---|---|")
    for k in range(1, steps + 1):
        for rec in recs.values():
            rec.optimize(1)
        if k in marks:
            a = recs["A"].gmap.params["means"].detach()
            cells = []
            for n in ("A'", "B", "T"):
                b = recs[n].gmap.params["means"].detach()
                if b.shape != a.shape:
                    cells.append(f"{len(b)} vs {len(a)} Gaussians")
                    continue
                d = (a - b).norm(dim=1)
                cells.append(f"{d.median():.1e} / {d.quantile(0.9):.1e} / {d.max():.1e}")
            print(f"| {k} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--one", type=int, default=3)
    ap.add_argument("--chain", type=int, default=200)
    ap.add_argument("--data", type=Path, default=KITCHEN)
    a = ap.parse_args()
    from eligsir_o3d.datasets import open_sequence

    seq, sets = open_sequence(a.data), kernel_sets()
    if a.one:
        one(restore(a.checkpoint, seq, sets["B"]), sets, a.one)
    if a.chain:
        chain(a.checkpoint, seq, sets, a.chain)


if __name__ == "__main__":
    main()
