"""Repeatability on a device: the same frames mapped twice, and once resumed from a checkpoint halfway.

    python benchmarks/reliability/repeatability.py --device cuda:0 --renderer gsplat --frames 40
    python benchmarks/reliability/repeatability.py --device cpu --renderer cpu --frames 12 --data synthetic   # self-check
    python benchmarks/reliability/repeatability.py --device cpu --renderer cpu --scale 0.25 --perturb 1e-7   # emulated drift

Every run uses the same seed, the same update count per frame and a fixed supervision scale (the fidelity policy
ablated, so that no clock enters), so on the CPU the three maps are bit-identical and the script prints zeros. On
CUDA, gsplat's backward (and torch's index_add) accumulates gradients with atomics in whatever order the threads
arrive, so the runs drift apart; the script measures by how much: the largest parameter difference, and the held-out
PSNR (every 8th frame, offset 4, never mapped) of each run. One JSON line per run, then a summary line.
``--perturb EPS`` emulates that on the CPU: each run's gradients get its own relative noise of size EPS.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]

import eligsir_o3d as eo3d  # noqa: E402
from eligsir_o3d.datasets import open_sequence  # noqa: E402
from eligsir_o3d.eval.metrics import psnr  # noqa: E402
from eligsir_o3d.core.gaussians import GaussianMap  # noqa: E402


def _perturb_gradients(eps: float, seed: int) -> None:
    """Multiply every gradient element by (1 + eps * N(0, 1)) before each Adam step: on the CPU, a stand-in for the
    reordered float32 sums of GPU atomics (one rounding step is ~6e-8 relative), to see how far that alone drifts."""
    gen = torch.Generator().manual_seed(seed)
    step = GaussianMap.step

    def perturbed(self):
        for p in self.params.values():
            if p.grad is not None:
                p.grad.mul_(1.0 + eps * torch.randn(p.grad.shape, generator=gen).to(p.grad))
        step(self)

    perturbed.original = getattr(step, "original", step)
    GaussianMap.step = perturbed


def _map(seq, args, frames, rec=None):
    if rec is None:
        cfg = eo3d.Config(seed=0, renderer=args.renderer, ablate=("fidelity",), fixed_scale=args.scale)
        cfg.depth_scale = seq.depth_scale
        rec = eo3d.Reconstructor(seq.intrinsic, args.device, cfg)
    for i in frames:
        rec.integrate(seq.frame(i, depth_max=rec.config.depth_max), updates=args.updates)
    return rec


def _score(seq, rec, held) -> float:
    return float(np.mean([psnr(rec.render(seq.frame(i).T_world_cam).color, seq.frame(i).color.to(rec.device))
                          for i in held]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"))
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--updates", type=int, default=4, help="updates per mapped frame")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--renderer", default="auto")
    ap.add_argument("--scale", type=float, default=1.0, help="supervision scale (the fidelity policy is fixed)")
    ap.add_argument("--perturb", type=float, default=0.0,
                    help="relative gradient noise per run (a CPU stand-in for GPU atomics; 0: none)")
    args = ap.parse_args(argv)

    seq = open_sequence(args.data)
    n = min(len(seq), args.frames)
    held = [i for i in range(n) if i % 8 == 4]
    source = [i for i in range(n) if i % 8 != 4]
    half = len(source) // 2
    runs = {}
    for k, name in enumerate(("first", "second", "resumed")):
        if args.perturb:
            GaussianMap.step = getattr(GaussianMap.step, "original", GaussianMap.step)
            _perturb_gradients(args.perturb, seed=k)
        t0 = time.perf_counter()
        if name == "resumed":
            rec = _map(seq, args, source[:half])
            with tempfile.TemporaryDirectory() as tmp:
                rec.save(Path(tmp) / "checkpoint.pt")
                rec = eo3d.Reconstructor.load(Path(tmp) / "checkpoint.pt", device=args.device)
            rec = _map(seq, args, source[half:], rec)
        else:
            rec = _map(seq, args, source)
        rec.finalize()
        params = {k: v.detach().cpu().clone() for k, v in rec.gmap.params.items()}
        runs[name] = {"params": params, "psnr": _score(seq, rec, held), "seconds": time.perf_counter() - t0,
                      "gaussians": len(rec.gmap), "updates": rec.stats.updates, "renderer": rec.config.renderer}
        print(json.dumps({"run": name, **{k: v for k, v in runs[name].items() if k != "params"}}), flush=True)

    def max_diff(a, b) -> float | None:
        pa, pb = runs[a]["params"], runs[b]["params"]
        if any(pa[k].shape != pb[k].shape for k in pa):
            return None  # the populations diverged (a different number of Gaussians)
        return max(float((pa[k] - pb[k]).abs().max()) if pa[k].numel() else 0.0 for k in pa)

    summary = {"device": args.device, "renderer": runs["first"]["renderer"], "frames": n, "scale": args.scale,
               "perturb": args.perturb,
               "max_param_diff_second": max_diff("first", "second"),
               "max_param_diff_resumed": max_diff("first", "resumed"),
               "psnr_spread_db": max(r["psnr"] for r in runs.values()) - min(r["psnr"] for r in runs.values())}
    print(json.dumps({"summary": summary}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
