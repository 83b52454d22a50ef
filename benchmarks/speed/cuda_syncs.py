"""Host round trips of one mapping update on CUDA: every operation that makes the host wait for the GPU, by source line.

    python benchmarks/speed/cuda_syncs.py --data ../shared/data/7scenes_redkitchen_jpg1000 --frames 12 --updates 20

Maps ``--frames`` frames (so the views, microcells and MCMC state are warm), then runs ``--updates`` more updates
under ``torch.cuda.set_sync_debug_mode("warn")``, which warns at every synchronising call (``.item()``, ``.cpu()``,
``bool(tensor)``, ``nonzero``, a blocking copy); the warnings are counted by the line of this package (or of gsplat)
that made them. Prints one JSON line per source line with calls per update, most frequent first.
"""

from __future__ import annotations

import argparse
import json
import traceback
import warnings
from collections import Counter
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]

import eligsir_o3d as eo3d  # noqa: E402
from eligsir_o3d.datasets import open_sequence  # noqa: E402


def _site(stack: list[traceback.FrameSummary]) -> str:
    """The innermost frame in eligsir_o3d (or gsplat), as path:line function."""
    for fr in reversed(stack):
        if "eligsir_o3d" in fr.filename or "gsplat" in fr.filename:
            short = fr.filename[fr.filename.find("eligsir_o3d") if "eligsir_o3d" in fr.filename
                                else fr.filename.find("gsplat"):]
            return f"{short}:{fr.lineno} {fr.name}"
    return "(outside the package)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"))
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--updates", type=int, default=20)
    ap.add_argument("--renderer", default="gsplat")
    ap.add_argument("--device", default="cuda:0")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("cuda_syncs.py needs a CUDA device")

    seq = open_sequence(args.data)
    cfg = eo3d.Config(seed=0, renderer=args.renderer)
    cfg.depth_scale = seq.depth_scale
    rec = eo3d.Reconstructor(seq.intrinsic, args.device, cfg)
    rec.warmup()
    for i in range(min(args.frames, len(seq))):
        rec.integrate(seq.frame(i, depth_max=rec.config.depth_max), updates=4)
    torch.cuda.synchronize()

    sites: Counter[str] = Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" in str(message):
            sites[_site(traceback.extract_stack()[:-1])] += 1

    old = warnings.showwarning
    warnings.showwarning = record
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = record
            rec.optimize(args.updates)
    finally:
        torch.cuda.set_sync_debug_mode("default")
        warnings.showwarning = old
    total = sum(sites.values())
    print(json.dumps({"updates": args.updates, "renderer": rec.config.renderer, "gaussians": len(rec.gmap),
                      "syncs_per_update": round(total / args.updates, 2)}))
    for site, n in sites.most_common():
        print(json.dumps({"site": site, "per_update": round(n / args.updates, 2)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
