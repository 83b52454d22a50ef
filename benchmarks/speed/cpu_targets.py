"""The cpu renderer's kernels compiled for several CPU targets, timed side by side on this machine.

numba compiles for the CPU named by ``NUMBA_CPU_NAME`` with the features in ``NUMBA_CPU_FEATURES``; an empty
feature string means "the named CPU's own features" (without it numba adds the *host's* features, so
``NUMBA_CPU_NAME=haswell`` alone still emits AVX-512 on an AVX-512 host). One worker process per target
(``host``, ``haswell`` = AVX2, ``generic`` = baseline x86-64 SSE2, or any LLVM CPU name) loads the same scene
(``benchmarks/speed/render.py``'s) and the workers run in turn, round after round (A, B, C, A, B, C, ...), so that the
load of a shared machine drifts over all of them alike. Each round times, per target:

- ``fwd`` / ``fwdbwd``: the cpu renderer's forward and forward + backward (L1 colour + depth loss), as
  ``benchmarks/speed/render.py`` does;
- ``comp_fwd`` / ``comp_bwd``: the compositing kernels alone; ``proj_fwd`` / ``proj_bwd``: the projection kernels;
- ``dssim``: the D-SSIM kernel on the frame's colour at that size;
- ``update`` (``--update``): one whole mapping update at 1/4 scale (select, render, L1 + D-SSIM loss, backward,
  Adam) of a :class:`Reconstructor` that has integrated the first 20 frames of the kitchen.

Times are the main thread's CPU time with numba and torch on one thread (``--threads 1``, the default: a measure of
work that holds up on a shared machine), or the wall clock with ``--threads N``; the table gives the median over
rounds.

    python benchmarks/speed/cpu_targets.py --targets host haswell generic --rounds 7
    python benchmarks/speed/cpu_targets.py --update --rounds 9 --targets host haswell
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(os.environ.get("ELIGSIR_BENCH_ROOT") or Path(__file__).resolve().parents[2])

TARGET_ENV = {"host": {}, "haswell": {"NUMBA_CPU_NAME": "haswell", "NUMBA_CPU_FEATURES": ""},
              "generic": {"NUMBA_CPU_NAME": "generic"}}


def target_env(name: str) -> dict:
    """Environment of a worker: ``target`` or ``target@DIR`` (the package and scene loader of another checkout,
    e.g. the code before a change, timed in the same rounds)."""
    name, _, root = name.partition("@")
    name, _, features = name.partition("~")
    env = dict(TARGET_ENV.get(name, {"NUMBA_CPU_NAME": name, "NUMBA_CPU_FEATURES": ""}))
    if features:
        env.update(NUMBA_CPU_NAME=name if name != "host" else "host", NUMBA_CPU_FEATURES=features)
    env["PYTHONPATH"] = env["ELIGSIR_BENCH_ROOT"] = str(Path(root).resolve()) if root else str(ROOT)
    return env


def _label(t: str) -> str:
    name, _, root = t.partition("@")
    return f"{name}@{Path(root).name}" if root else name


# ------------------------------------------------------------------------------------------------ worker side ----

def worker(threads: int, gaussians: list[int], scales: list[float], reps: int, update: bool,
           blocks: list[int]) -> None:
    """One target's worker: loads the scenes, prints its info line, then one JSON line of timings per stdin line."""
    import numba
    import numpy as np
    import torch

    from eligsir_o3d.render import cpu_backend as cb

    torch.set_num_threads(threads)
    numba.set_num_threads(threads)
    clock = time.thread_time if threads == 1 else time.perf_counter
    first_call = cb.warmup()
    kern = _kernels()
    cases = _cases(gaussians, scales)
    if not blocks:
        blocks = [kern.k.default_block()] if hasattr(kern.k, "default_block") else [16]
    rec = _update_setup() if update else None
    info = {"numba_cpu_name": numba.config.CPU_NAME or "host", "threads": threads, "first_call_s": first_call}
    if hasattr(kern.k, "default_block"):
        info["default_block"] = kern.k.default_block()
    print(json.dumps({"info": info}), flush=True)

    def best(fn):
        ts = []
        for _ in range(reps):
            t0 = clock()
            fn()
            ts.append(clock() - t0)
        return min(ts)

    for _line in sys.stdin:
        rows = []
        for case in cases:
            row = {"gaussians": case[0], "scale": case[1]}
            _time_compositing(row, case, blocks, kern, best)
            _time_projection_and_dssim(row, case, kern, best)
            rows.append(row)
        if rec is not None:
            ts = []
            for _ in range(reps):
                t0 = clock()
                rec.optimize(1, scale=0.25)
                ts.append(clock() - t0)
            rows.append({"update_q": float(np.median(ts)), "update_gaussians": len(rec.gmap)})
        print(json.dumps({"rows": rows}), flush=True)


def _kernels():
    """The compiled kernels a worker times (of the code on its PYTHONPATH)."""
    from types import SimpleNamespace

    from eligsir_o3d.optim import dssim_kernels
    from eligsir_o3d.optim.losses import _window
    from eligsir_o3d.render import cpu_backend as cb

    return SimpleNamespace(cb=cb, k=cb._kernels(), pk=cb._proj_kernels(), dk=dssim_kernels, window=_window)


def _cases(gaussians: list[int], scales: list[float]) -> list[tuple]:
    """(gaussians, scale, params, camera, T_world_cam, colour [H, W, 3], depth [H, W]) of every scene and scale."""
    from benchmarks.speed.render import BASE, load_scene, resize  # PYTHONPATH=the target's root (target_env)

    cases = []
    for n in gaussians:
        params, color0, depth0, T0 = load_scene(n)
        for s in scales:
            cam = BASE.scaled(s)
            cases.append((n, s, params, cam, T0, resize(color0, cam.width, cam.height),
                          resize(depth0, cam.width, cam.height)))
    return cases


def _time_compositing(row: dict, case: tuple, blocks: list[int], kern, best) -> None:
    """The renderer's forward and forward + backward, and the compositing kernels alone, per block size."""
    import numpy as np
    import torch

    from benchmarks.speed.render import render_steps  # PYTHONPATH=the target's root (target_env)
    from eligsir_o3d.render.cpu_backend import CpuRenderer, bin_tiles_csr, project_cpu

    _, _, params, cam, T0, rgb, dep = case
    cb, k = kern.cb, kern.k
    with torch.no_grad():  # the kernels alone, on this view's inputs
        proj = project_cpu(params["means"], params["quats"], params["scales"], cam, T0)
        offsets, flat, tiles_x = bin_tiles_csr(proj, cam.width, cam.height)
    f32 = np.float32
    m, c = proj.means2d.numpy().astype(f32), proj.conics.numpy().astype(f32)
    o = params["opacities"].numpy().astype(f32)
    feats = np.concatenate([params["colors"].numpy(), proj.depths.numpy()[:, None]], 1).astype(f32)
    order = np.argsort(-(offsets[1:] - offsets[:-1]).numpy(), kind="stable")
    bounds = np.empty((m.shape[0], 3), f32)
    k.cull_bounds(c, o, bounds)
    H, W = cam.height, cam.width
    of, oa, oT, ol = (np.empty((H, W, 4), f32), np.empty((H, W), f32), np.empty((H, W), f32),
                      np.empty((H, W), np.int32))
    off, fl = offsets.numpy(), flat.numpy()
    gf, ga = np.full((H, W, 4), 0.01, f32), np.full((H, W), 0.01, f32)
    v = np.empty((fl.shape[0], getattr(k, "ISECT_COLS", 10)), f32)  # by code version: rows padded to a vector
    for blk in blocks:
        sfx = "" if blk == blocks[0] else f"_{blk}"
        comp = getattr(cb, "_compositors", None) or getattr(k, "compositors", None)  # by code version
        renderer = CpuRenderer(block=blk) if comp is not None else CpuRenderer()
        ps = {kk: vv.clone().requires_grad_(True) for kk, vv in params.items()}
        fwd, fwdbwd = render_steps(renderer, ps, cam, T0, torch.zeros(3), rgb, dep)
        row["fwd" + sfx] = best(fwd)
        row["fwdbwd" + sfx] = best(fwdbwd)
        kf, kb = comp(blk) if comp is not None else (k.composite_forward, k.composite_backward)
        if hasattr(k, "task_slots"):  # by code version: the forward gathers the tiles once for the backward
            gathered = k.gather_buffers(fl.shape[0], off.shape[0] - 1, blk)
            slots = k.task_slots(order.shape[0])
            row["comp_fwd" + sfx] = best(lambda: k.run(kf, m, c, o, feats, bounds, off, fl, order, slots, tiles_x, W,
                                                       H, of, oa, oT, ol, *gathered))
            vg = np.empty((m.shape[0], 10), f32)
            row["comp_bwd" + sfx] = best(lambda: k.run(kb, *gathered, off, fl, order, slots, tiles_x, W, H, oT, ol, gf,
                                                       ga, v, vg))
        else:
            row["comp_fwd" + sfx] = best(lambda: k.run(kf, m, c, o, feats, bounds, off, fl, order, tiles_x, W, H,
                                                       of, oa, oT, ol))
            row["comp_bwd" + sfx] = best(lambda: k.run(kb, m, c, o, feats, bounds, off, fl, order, tiles_x, W, H,
                                                       oT, ol, gf, ga, v))


def _time_projection_and_dssim(row: dict, case: tuple, kern, best) -> None:
    """The projection kernels (forward, backward) and the D-SSIM kernel, on this view's inputs."""
    import numpy as np
    import torch

    _, _, params, cam, T0, rgb, _ = case
    cb, pk, f32 = kern.cb, kern.pk, np.float32
    from eligsir_o3d.render.projection import world_to_cam
    V = world_to_cam(T0, "cpu", torch.float32).double().numpy()
    camv = np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cb.NEAR, cb.EPS2D])
    mq, qq, sq = (params[kk].numpy().astype(f32) for kk in ("means", "quats", "scales"))
    nn = mq.shape[0]
    o2, o3, o1, orad = np.empty((nn, 2), f32), np.empty((nn, 3), f32), np.empty(nn, f32), np.empty(nn, np.int32)
    row["proj_fwd"] = best(lambda: pk.project_forward(mq, qq, sq, V, camv, o2, o3, o1, orad))
    g2, g3, g1 = np.full((nn, 2), 0.1, f32), np.full((nn, 3), 0.1, f32), np.full(nn, 0.1, f32)
    r3, r4, r3b = np.empty((nn, 3), f32), np.empty((nn, 4), f32), np.empty((nn, 3), f32)
    row["proj_bwd"] = best(lambda: pk.project_backward(mq, qq, sq, V, camv, g2, g3, g1, r3, r4, r3b))
    x = np.ascontiguousarray(rgb.permute(2, 0, 1).numpy(), f32)
    y = np.ascontiguousarray(np.clip(x + 0.05, 0, 1), f32)
    win = np.asarray(kern.window(11, 1.5), f32)
    grad = np.empty_like(x)
    row["dssim"] = best(lambda: kern.dk.dssim_value_and_grad(x, y, win, grad))


def _update_setup():
    from eligsir_o3d import Config, Reconstructor
    from eligsir_o3d.datasets import open_sequence
    seq = open_sequence(ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000")
    cfg = Config(renderer="cpu")
    rec = Reconstructor(seq.camera, device="cpu", config=cfg)
    for i in range(20):
        rec.integrate(seq.frame(i, depth_max=cfg.depth_max), updates=0)
    rec.optimize(3, scale=0.25)  # compile / load the update's kernels
    return rec


# ------------------------------------------------------------------------------------------------ driver side ----

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", nargs="+", default=["host", "haswell", "generic"],
                    help="host, haswell, generic or an LLVM CPU name; NAME@DIR runs another checkout's code")
    ap.add_argument("--gaussians", type=int, nargs="+", default=[20000, 5000])
    ap.add_argument("--scales", type=float, nargs="+", default=[0.25, 0.5])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=3, help="timed runs per round (the best counts)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--update", action="store_true", help="also time whole 1/4-scale mapping updates")
    ap.add_argument("--blocks", type=int, nargs="*", default=[],
                    help="compositing block sizes to time (pixels; default: the one each target chooses)")
    ap.add_argument("--json", type=Path, help="write every round's figures here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.threads, args.gaussians, args.scales, args.reps, args.update, args.blocks)
        return 0
    import numpy as np
    base = [sys.executable, __file__, "--worker", "--threads", str(args.threads), "--reps", str(args.reps),
            "--gaussians", *map(str, args.gaussians), "--scales", *map(str, args.scales)]
    if args.update:
        base.append("--update")
    if args.blocks:
        base += ["--blocks", *map(str, args.blocks)]
    procs, infos = {}, {}
    for t in args.targets:
        env = dict(os.environ, **target_env(t))
        if args.threads == 1:
            env["OMP_WAIT_POLICY"] = "PASSIVE"
        procs[t] = subprocess.Popen(base, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    for t, p in procs.items():
        infos[t] = json.loads(p.stdout.readline())["info"]
    print(f"# loadavg at start {' '.join(open('/proc/loadavg').read().split()[:3])}; clock="
          f"{'main-thread CPU time, 1 thread' if args.threads == 1 else f'wall, {args.threads} threads'}; "
          f"median over {args.rounds} rounds of the best of {args.reps}")
    for t in args.targets:
        print(f"# {t}: {json.dumps(infos[t])}")
    results = {t: [] for t in args.targets}
    for r in range(args.rounds):
        for t, p in procs.items():
            p.stdin.write("go\n")
            p.stdin.flush()
            results[t].append(json.loads(p.stdout.readline())["rows"])
    for p in procs.values():
        p.stdin.close()
        p.wait()
    print(f"# loadavg at end {' '.join(open('/proc/loadavg').read().split()[:3])}")
    keys = ["fwd", "fwdbwd", "comp_fwd", "comp_bwd", "proj_fwd", "proj_bwd", "dssim"]
    keys += [f"{kk}_{b}" for b in args.blocks[1:] for kk in ("fwd", "fwdbwd", "comp_fwd", "comp_bwd")]
    print(f"{'target':>16} {'WxH':>9} {'gauss':>6} " + " ".join(f"{k:>11}" for k in keys) + "   (ms)")
    n_cases = len(args.gaussians) * len(args.scales)
    for ci in range(n_cases):
        for t in args.targets:
            rows = [rr[ci] for rr in results[t]]
            w, h = int(round(640 * rows[0]["scale"])), int(round(480 * rows[0]["scale"]))
            med = [1e3 * float(np.median([row[k] for row in rows])) for k in keys]
            print(f"{_label(t):>16} {w:>4}x{h:<4} {rows[0]['gaussians']:>6} " + " ".join(f"{x:11.2f}" for x in med))
    if args.update:
        for t in args.targets:
            u = [rr[-1]["update_q"] for rr in results[t]]
            print(f"{_label(t):>16} update at 1/4 scale: median {1e3 * float(np.median(u)):.1f} ms "
                  f"({results[t][-1][-1]['update_gaussians']} Gaussians at the end)")
    if args.json:
        args.json.write_text(json.dumps({"info": infos, "rounds": results}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
