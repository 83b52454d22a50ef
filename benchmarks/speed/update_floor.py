"""The host floor of a mapping update on the CPU path or the CUDA code path, side by side for two (or more)
checkouts of the package.

    git -C . worktree add /tmp/old 4fbcc29
    python benchmarks/speed/update_floor.py --code old=/tmp/old --code new=.
    python benchmarks/speed/update_floor.py --path cuda --code old=/tmp/old --code new=.

What an update costs when its kernels cost (almost) nothing: a Reconstructor of the embedded synthetic room at
64x48 (3 frames integrated, 4 updates each; area supervision; no MCMC relocation round in the timed updates) on the
CPU path (``renderer="cpu"``, the checkout's default kernels), updates at 1/4 scale: a 16x12 image and a few
dozen Gaussians. Python, torch's dispatch, autograd's engine and the calls into the compiled kernels are what is
left. Only public API that every checkout has is used (``Config``, ``Reconstructor``, ``open_sequence``), so any
commit can be timed. One worker process per checkout (``NAME=DIR``: ``DIR/eligsir_o3d`` is the package timed),
one torch and numba thread; the workers take turns round after round, so that the load of a shared machine falls
on all alike. Per round each runs ``--warm`` untimed updates and times ``--updates`` one by one; the table gives
the median over all timed updates (process CPU time and wall clock) and the ratio to the first checkout.

``--path cuda`` times the code a CUDA map runs, on the CPU, as a GPU's host would see it, kernels costing nothing:
- the renderer is the gsplat backend on gsplat's CPU stand-in (``tests/helpers/gsplat_standin.py``), its forward
  and backward timed apart and left out (on a GPU they are gsplat's few asynchronous launches);
- a checkout with a kernel set (``eligsir_o3d/kernels/device.py``) runs ``kernels="fused"``; each Triton kernel
  runs once per argument shape under Triton's interpreter, and later launches of that shape replay the tensors it
  wrote (copied in); the kernel's run (interpreted or replayed) is timed apart and left out, the host work of ours
  around it remains; the Triton launches per update are printed (on a GPU each adds its launcher's host cost);
- an older checkout runs from a copy whose ``device.type == "cpu"`` tests are rewritten to fail (its numba and
  CPU-only branches off: the torch operators a CUDA map dispatches, each costing its dispatch).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class _Left:
    """Seconds spent in work that the CUDA path's host does not do (the stand-in, replays), to be left out."""

    seconds = 0.0


def _timed_out(fn):
    import time

    def run(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            _Left.seconds += time.perf_counter() - t0

    return run


def _gsplat_on_standin(device: str):
    """The checkout's GsplatRenderer on gsplat's CPU stand-in, the stand-in's forward and backward left out."""
    import importlib.util

    import pytest
    import torch

    from eligsir_o3d.render.gsplat_backend import GsplatRenderer

    spec = importlib.util.spec_from_file_location("gsplat_standin", ROOT / "tests" / "helpers" / "gsplat_standin.py")
    standin = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(standin)
    rasterization = standin.patch(pytest.MonkeyPatch())

    class Raster(torch.autograd.Function):
        @staticmethod
        def forward(ctx, means, quats, scales, opacities, colors, viewmats, Ks, width, height, kw):
            def fwd():
                with torch.enable_grad():
                    ins = [t.detach().requires_grad_(t.requires_grad) for t in (means, quats, scales, opacities,
                                                                                 colors)]
                    return ins, rasterization(*ins, viewmats, Ks, width, height,
                                              **{k: v for k, v in kw.items() if k != "meta"})
            ins, (rendered, alphas, meta) = _timed_out(fwd)()
            ctx.ins, ctx.outs = ins, (rendered, alphas)
            kw["meta"] = meta  # gsplat's meta (radii, means2d, ...), which older checkouts read
            return rendered.detach(), alphas.detach()

        @staticmethod
        def backward(ctx, g_rendered, g_alphas):
            def bwd():
                need = [t for t in ctx.ins if t.requires_grad]
                grads = iter(torch.autograd.grad(ctx.outs, need, (g_rendered, g_alphas), allow_unused=True))
                out = [next(grads) if t.requires_grad else None for t in ctx.ins]
                ctx.ins = ctx.outs = None  # the stand-in's graph is freed here, not in the update's own time
                return out
            return (*_timed_out(bwd)(), None, None, None, None, None)

    def raster(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        box = dict(kw)
        rendered, alphas = Raster.apply(means, quats, scales, opacities, colors, viewmats, Ks, width, height, box)
        meta = box.pop("meta")
        return rendered, alphas, {k: v.detach() if hasattr(v, "detach") else v for k, v in meta.items()}

    return GsplatRenderer(device, rasterization=raster)


def _replayed_triton() -> None:
    """Each Triton kernel runs once per argument shape; later launches copy in the tensors that run wrote."""
    import torch

    from eligsir_o3d.kernels import triton_launch

    real, seen = triton_launch._run, {}

    def run(k, grid, device, args, meta):
        key = (k, tuple(grid), tuple(tuple(a.shape) if isinstance(a, torch.Tensor) else None for a in args))
        if key in seen:
            for i, v in seen[key]:
                args[i].copy_(v)
            return
        before = [a.clone() if isinstance(a, torch.Tensor) else None for a in args]
        real(k, grid, device, args, meta)
        seen[key] = [(i, a.clone()) for i, (a, b) in enumerate(zip(args, before))
                     if b is not None and not torch.equal(a, b)]

    triton_launch._run = _timed_out(run)


def _cuda_branches(directory: Path) -> Path:
    """A copy of the checkout's package whose ``device.type == "cpu"`` tests fail (its CUDA branches on the CPU)."""
    import re
    import shutil
    import tempfile

    out = Path(tempfile.mkdtemp(prefix="cuda_path_"))
    shutil.copytree(directory / "eligsir_o3d", out / "eligsir_o3d")
    for f in (out / "eligsir_o3d").rglob("*.py"):
        if f.name in ("reconstructor_state.py", "calibrate.py", "clocks.py"):
            continue
        text = f.read_text()
        new = re.sub(r'\.type (==|!=) "cpu"', r'.type \1 "not-cpu"', text)
        if new != text:
            f.write_text(new)
    return out


def worker(warm: int, updates: int, path: str) -> None:
    """Build the room's map, then per line on stdin one round: ``warm`` updates, ``updates`` timed; a JSON line of
    (cpu seconds, wall seconds) per update on stdout, the left-out seconds (``--path cuda``) taken off both."""
    import time

    import eligsir_o3d as eo3d

    eo3d.Config  # a public name first: the package's process set-up (numba's threading layer) before torch
    import numba
    import torch
    from eligsir_o3d.datasets import open_sequence

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    cfg = eo3d.Config(seed=0, renderer="cpu" if path == "cpu" else "torch")
    fused = path == "cuda" and (Path(eo3d.__file__).parent / "kernels" / "device.py").exists()
    if fused:
        cfg.optim.kernels = "fused"
        _replayed_triton()
    cfg.supervision.mode = "area"
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 10 ** 6, 10 ** 6
    rec = eo3d.Reconstructor(seq.camera, "cpu", cfg)
    if path == "cuda":
        rec.renderer = _gsplat_on_standin("cpu")
    for i in range(len(seq)):
        rec.integrate(seq.frame(i), updates=4)
    rec.optimize(3, scale=0.25)
    launches = None
    if fused:
        from eligsir_o3d.kernels import triton_launch

        n0 = triton_launch.launch_count()
        rec.optimize(10, scale=0.25)
        launches = (triton_launch.launch_count() - n0) / 10
    info = {"package": str(Path(eo3d.__file__).parent), "gaussians": len(rec.gmap), "triton_launches": launches}
    print(json.dumps(info), flush=True)
    for _ in sys.stdin:
        rec.optimize(warm, scale=0.25)
        times = []
        for _ in range(updates):
            left = _Left.seconds
            c0, w0 = time.process_time(), time.perf_counter()
            rec.optimize(1, scale=0.25)
            c, w = time.process_time() - c0, time.perf_counter() - w0
            left = _Left.seconds - left
            times.append((c - left, w - left))
        print(json.dumps(times), flush=True)


def _spawn(directory: Path, warm: int, updates: int, path: str, copies: list[Path]) -> subprocess.Popen:
    if path == "cuda" and not (directory / "eligsir_o3d" / "kernels" / "device.py").exists():
        directory = _cuda_branches(directory.resolve())
        copies.append(directory)
    env = dict(os.environ, PYTHONPATH=str(directory.resolve()), OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, __file__, "--worker", "--warm", str(warm), "--updates", str(updates),
                             "--path", path],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))


def run(codes: dict[str, Path], rounds: int, warm: int, updates: int, path: str = "cpu") -> dict:
    """Per checkout: its worker's info and every timed update, the workers taking turns round after round."""
    import shutil

    copies: list[Path] = []  # rewritten packages (--path cuda), removed at the end
    procs = {name: _spawn(d, warm, updates, path, copies) for name, d in codes.items()}
    try:
        out = {name: {"info": json.loads(p.stdout.readline()), "cpu": [], "wall": []} for name, p in procs.items()}
        for _ in range(rounds):
            for name, p in procs.items():
                p.stdin.write("round\n")
                p.stdin.flush()
                for c, w in json.loads(p.stdout.readline()):
                    out[name]["cpu"].append(c)
                    out[name]["wall"].append(w)
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait(timeout=60)
        for c in copies:
            shutil.rmtree(c, ignore_errors=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--code", action="append", default=[], metavar="NAME=DIR",
                    help="a checkout to time (repeat; the first is the baseline); default: this one")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--updates", type=int, default=20, help="timed updates per worker per round")
    ap.add_argument("--warm", type=int, default=3, help="untimed updates before each round's")
    ap.add_argument("--path", choices=("cpu", "cuda"), default="cpu",
                    help="the CPU path, or the CUDA code path with its kernels left out (see above)")
    ap.add_argument("--json", type=Path, help="write every timed update here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.warm, args.updates, args.path)
        return 0
    codes = dict(c.split("=", 1) for c in args.code) if args.code else {"this": str(ROOT)}
    res = run({k: Path(v) for k, v in codes.items()}, args.rounds, args.warm, args.updates, args.path)
    first = next(iter(res))
    med = {k: {c: 1e3 * statistics.median(r[c]) for c in ("cpu", "wall")} for k, r in res.items()}
    print(f"# {args.path} path; load average at end: {os.getloadavg()}")
    for k, r in res.items():
        if r["info"].get("triton_launches") is not None:
            print(f"# {k}: {r['info']['triton_launches']:.1f} Triton launches per update (their host side timed)")
    print(f"{'code':>8} {'gaussians':>9} {'cpu ms':>8} {'wall ms':>8} {'cpu ratio':>10} {'wall ratio':>10}")
    for k, r in res.items():
        print(f"{k:>8} {r['info']['gaussians']:>9} {med[k]['cpu']:8.3f} {med[k]['wall']:8.3f} "
              f"{med[first]['cpu'] / med[k]['cpu']:10.2f} {med[first]['wall'] / med[k]['wall']:10.2f}")
    if args.json:
        args.json.write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
