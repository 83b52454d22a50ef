"""One mapping update under ``torch.profiler``: launches, synchronisations and copies per update as the device
runtime saw them, GPU-busy and host milliseconds per update, milliseconds per admitted frame, and the update's
time on maps of a given size in view. The GPU check of a lent machine (``benchmarks/platforms/gpu_offline.sh
check`` runs it); on a CPU it runs too, and reports the operators and host time alone.

    python benchmarks/speed/update_profile.py --data ../shared/data/7scenes_redkitchen_jpg1000 --device cuda:0
    python benchmarks/speed/update_profile.py --device cuda:0 --in-view 20000 200000 --json /tmp/profile.json

The map: ``--frames`` frames of ``--data`` (default: the embedded room) integrated with ``--warm-updates`` updates
each at the configured renderer and kernel set (``auto``: gsplat and the fused kernels on CUDA), MCMC relocation
rounds off so that every counted update is alike. Counted over ``--updates`` updates at 1/4 scale:

- launches: the runtime's kernel launch calls (``cudaLaunchKernel``, ``cuLaunchKernel``, Triton's and gsplat's
  included);
- syncs: the runtime's synchronising calls (``cudaStreamSynchronize``, ``cudaDeviceSynchronize``,
  ``cudaEventSynchronize``, a blocking ``cudaMemcpy``);
- copies: the runtime's memcpy calls, asynchronous ones included;
- GPU-busy: the summed duration of the device's kernels and copies;
- host: the wall time of ``--updates`` updates without the profiler, the device synchronised at both ends.

Per frame: the wall time of integrating ``--frames-timed`` more frames with no update (admission, support probe,
growth, the views' bookkeeping). ``--in-view N ...``: the map grown to N Gaussians in the first view (points of its
depth with a little jitter), then the same host timing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter

import torch

LAUNCH = ("LaunchKernel",)
SYNC = ("StreamSynchronize", "DeviceSynchronize", "EventSynchronize")


def build(data: str, device: str, frames: int, warm_updates: int, renderer: str, kernels: str):
    import eligsir_o3d as eo3d
    from eligsir_o3d.datasets import open_sequence

    seq = open_sequence(data)
    cfg = eo3d.Config(seed=0, renderer=renderer)
    cfg.optim.kernels = kernels
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 10 ** 9, 10 ** 9
    rec = eo3d.Reconstructor(seq.camera, device, cfg)
    for i in range(min(frames, len(seq))):
        rec.integrate(seq.frame(i), updates=warm_updates)
    return rec, seq


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def host_ms(rec, device: str, updates: int, rounds: int = 3) -> float:
    """Median over ``rounds`` of the wall ms per update of ``updates`` updates at 1/4 scale."""
    times = []
    for _ in range(rounds):
        rec.optimize(2, scale=0.25)
        _sync(device)
        t0 = time.perf_counter()
        rec.optimize(updates, scale=0.25)
        _sync(device)
        times.append(1e3 * (time.perf_counter() - t0) / updates)
    return sorted(times)[len(times) // 2]


def profile(rec, device: str, updates: int) -> dict:
    """Runtime calls per update and GPU-busy ms per update over ``updates`` profiled updates."""
    from torch.profiler import ProfilerActivity, profile as torch_profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    rec.optimize(2, scale=0.25)
    _sync(device)
    with torch_profile(activities=activities) as prof:
        rec.optimize(updates, scale=0.25)
        _sync(device)
    runtime, ops, busy_us = Counter(), Counter(), 0.0
    for e in prof.events():
        if e.device_type == torch.autograd.DeviceType.CUDA:
            busy_us += e.time_range.elapsed_us()
        elif e.name.startswith(("cuda", "cu")):
            runtime[e.name] += 1
        elif e.name.startswith("aten::"):
            ops[e.name] += 1
    per = 1.0 / updates
    out = {
        "launches": per * sum(n for k, n in runtime.items() if any(s in k for s in LAUNCH)),
        "syncs": per * sum(n for k, n in runtime.items()
                           if any(s in k for s in SYNC) or k in ("cudaMemcpy", "cuMemcpy")),
        "copies": per * sum(n for k, n in runtime.items() if "Memcpy" in k),
        "gpu_busy_ms": 1e-3 * busy_us * per,
        "aten_ops": per * sum(ops.values()),
        "runtime_calls": {k: round(per * n, 2) for k, n in runtime.most_common(12)},
        "top_ops": {k: round(per * n, 2) for k, n in ops.most_common(12)},
    }
    return out


def frame_ms(rec, seq, start: int, count: int, device: str) -> float | None:
    """Mean wall ms to integrate frames ``start..start+count-1`` of ``seq`` with no update (None: none left)."""
    idx = list(range(start, min(start + count, len(seq))))
    if not idx:
        return None
    _sync(device)
    t0 = time.perf_counter()
    for i in idx:
        rec.integrate(seq.frame(i), updates=0)
    _sync(device)
    return 1e3 * (time.perf_counter() - t0) / len(idx)


@torch.no_grad()
def grow_in_view(rec, frame, n: int, seed: int = 0) -> None:
    """Add Gaussians at random valid depth pixels of ``frame`` (jittered by a few mm) until the map holds ``n``."""
    extra = n - len(rec.gmap)
    if extra <= 0:
        return
    g = torch.Generator().manual_seed(seed)
    depth, color = frame.depth.cpu(), frame.color.cpu()
    vs, us = torch.nonzero(depth > 0, as_tuple=True)
    pick = torch.randint(0, len(vs), (extra,), generator=g)
    v, u = vs[pick], us[pick]
    pts = frame.camera.unproject(u.float(), v.float(), depth[v, u], frame.T_world_cam)
    pts = pts + 0.003 * torch.randn(pts.shape, generator=g)
    rec.gmap.add(pts.to(rec.device), color[v, u].to(rec.device), torch.full((extra,), 0.01), 0.5)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="synthetic")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--renderer", default="auto")
    ap.add_argument("--kernels", default="auto")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--warm-updates", type=int, default=4)
    ap.add_argument("--updates", type=int, default=20)
    ap.add_argument("--frames-timed", type=int, default=10)
    ap.add_argument("--in-view", type=int, nargs="*", default=[])
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    rec, seq = build(args.data, args.device, args.frames, args.warm_updates, args.renderer, args.kernels)
    out = {"device": args.device, "renderer": rec.renderer.name, "kernels": rec.kernels.name,
           "gaussians": len(rec.gmap)}
    out["profile"] = profile(rec, args.device, args.updates)
    out["host_ms"] = host_ms(rec, args.device, args.updates)
    out["in_view"] = rec.last_in_view
    out["frame_ms"] = frame_ms(rec, seq, args.frames, args.frames_timed, args.device)
    first = seq.frame(0)
    out["maps"] = []
    for n in args.in_view:
        grow_in_view(rec, first, n)
        ms = host_ms(rec, args.device, args.updates)
        out["maps"].append({"gaussians": len(rec.gmap), "in_view": rec.last_in_view, "ms_per_update": ms})
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
