"""The host floor of a mapping update on the CPU path, side by side for two (or more) checkouts of the package.

    git -C . worktree add /tmp/old 4fbcc29
    python benchmarks/speed/update_floor.py --code old=/tmp/old --code new=.

What an update costs when its kernels cost (almost) nothing: a Reconstructor of the embedded synthetic room at
64x48 (3 frames integrated, 4 updates each; area supervision; no MCMC relocation round in the timed updates) on the
CPU path (``renderer="cpu"``, the checkout's default kernels), updates at 1/4 scale: a 16x12 image and a few
dozen Gaussians. Python, torch's dispatch, autograd's engine and the calls into the compiled kernels are what is
left. Only public API that every checkout has is used (``Config``, ``Reconstructor``, ``open_sequence``), so any
commit can be timed. One worker process per checkout (``NAME=DIR``: ``DIR/eligsir_o3d`` is the package timed),
one torch and numba thread; the workers take turns round after round, so that the load of a shared machine falls
on all alike. Per round each runs ``--warm`` untimed updates and times ``--updates`` one by one; the table gives
the median over all timed updates (process CPU time and wall clock) and the ratio to the first checkout.
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


def worker(warm: int, updates: int) -> None:
    """Build the room's map, then per line on stdin one round: ``warm`` updates, ``updates`` timed; a JSON line of
    (cpu seconds, wall seconds) per update on stdout."""
    import time

    import eligsir_o3d as eo3d

    eo3d.Config  # a public name first: the package's process set-up (numba's threading layer) before torch
    import numba
    import torch
    from eligsir_o3d.datasets import open_sequence

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    seq = open_sequence("synthetic", n_frames=3, width=64, height=48)
    cfg = eo3d.Config(seed=0, renderer="cpu")
    cfg.supervision.mode = "area"
    cfg.growth.mcmc.refine_start, cfg.growth.mcmc.refine_every = 10 ** 6, 10 ** 6
    rec = eo3d.Reconstructor(seq.camera, "cpu", cfg)
    for i in range(len(seq)):
        rec.integrate(seq.frame(i), updates=4)
    rec.optimize(3, scale=0.25)
    info = {"package": str(Path(eo3d.__file__).parent), "gaussians": len(rec.gmap)}
    print(json.dumps(info), flush=True)
    for _ in sys.stdin:
        rec.optimize(warm, scale=0.25)
        times = []
        for _ in range(updates):
            c0, w0 = time.process_time(), time.perf_counter()
            rec.optimize(1, scale=0.25)
            times.append((time.process_time() - c0, time.perf_counter() - w0))
        print(json.dumps(times), flush=True)


def _spawn(directory: Path, warm: int, updates: int) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(directory.resolve()), OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, __file__, "--worker", "--warm", str(warm), "--updates", str(updates)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))


def run(codes: dict[str, Path], rounds: int, warm: int, updates: int) -> dict:
    """Per checkout: its worker's info and every timed update, the workers taking turns round after round."""
    procs = {name: _spawn(d, warm, updates) for name, d in codes.items()}
    out = {name: {"info": json.loads(p.stdout.readline()), "cpu": [], "wall": []} for name, p in procs.items()}
    try:
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
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--code", action="append", default=[], metavar="NAME=DIR",
                    help="a checkout to time (repeat; the first is the baseline); default: this one")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--updates", type=int, default=20, help="timed updates per worker per round")
    ap.add_argument("--warm", type=int, default=3, help="untimed updates before each round's")
    ap.add_argument("--json", type=Path, help="write every timed update here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.warm, args.updates)
        return 0
    codes = dict(c.split("=", 1) for c in args.code) if args.code else {"this": str(ROOT)}
    res = run({k: Path(v) for k, v in codes.items()}, args.rounds, args.warm, args.updates)
    first = next(iter(res))
    med = {k: {c: 1e3 * statistics.median(r[c]) for c in ("cpu", "wall")} for k, r in res.items()}
    print(f"# load average at end: {os.getloadavg()}")
    print(f"{'code':>8} {'gaussians':>9} {'cpu ms':>8} {'wall ms':>8} {'cpu ratio':>10} {'wall ratio':>10}")
    for k, r in res.items():
        print(f"{k:>8} {r['info']['gaussians']:>9} {med[k]['cpu']:8.3f} {med[k]['wall']:8.3f} "
              f"{med[first]['cpu'] / med[k]['cpu']:10.2f} {med[first]['wall'] / med[k]['wall']:10.2f}")
    if args.json:
        args.json.write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
