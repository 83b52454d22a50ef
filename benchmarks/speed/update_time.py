"""One mapping update at 1/4 scale, timed side by side for two (or more) checkouts of the package.

What :class:`Reconstructor` does per update (``rec.optimize(1, scale=0.25)``: view selection, the view's 160x120
supervision, render, loss, regularisers, backward, Adam, MCMC, the views' feedback), on the *same* map in every
checkout: the driver writes one 3DGS PLY per map size (``--gaussians``) from the kitchen's depth (frames 0..190,
every 10th, back-projected; ``n`` points at random; scales the nearest-neighbour distance; opacity 0.5, colour of
the pixel), and every worker loads it into a fresh Reconstructor of its own code whose views are the same 20
kitchen frames. ``--workers`` processes per checkout and thread count (a process's speed varies by a few per cent
from one start to the next, so their updates are pooled); the workers take turns round after round so that the
load of a shared machine falls on all alike. A worker loads the package's public names first, as the ``eligsir``
command and a user's script do, so that each checkout runs with its own process set-up (numba's threading layer,
OpenMP's wait policy; the info lines name them). Each round reloads the map, runs ``--warm`` updates untimed
and times ``--updates`` one by one; the table gives the median over all timed updates of all rounds and the ratio
to the first checkout.

Clock: the process's CPU time with one thread (a measure of work that holds up on a shared machine), the
wall clock with more. Threads: a worker with more than one thread follows each round's timed updates with as many
on a single thread (wall clock, after one untimed; consecutive updates, as a mapping run makes them, so the second
core's caches stay warm), and the report gives the median over rounds of the ratio of their medians beside the
ratio of the workers' medians; each such worker also times a compiled loop that parallelises perfectly, on one
thread and on its threads, once a round: what the machine's threads delivered at those moments (one shared 2-core
VM here ran it 1.1x to 2.0x faster on two threads, changing within seconds), to read an update's speed-up
against. ``--phases``: each phase's share and speed-up besides (``update_phases.py``). ``--in-view K``: every
map holds the same K Gaussians in the views (the map of size K) and its remaining ``n - K`` Gaussians out of every
view (copies of the kitchen's points shifted by tens of metres, those that some view could reach dropped), the
scene of a large map whose update sees one room; the table adds the Gaussians the updates supervised (median).
``NAME=DIR`` names a checkout (``DIR/eligsir_o3d`` is the package timed):

    git -C . worktree add /tmp/old c6a5f9a      # or: mkdir /tmp/old && git archive c6a5f9a | tar -x -C /tmp/old
    python benchmarks/speed/update_time.py --code old=/tmp/old --code new=. --gaussians 5000 20000 --threads 1 2
    python benchmarks/speed/update_time.py --in-view 20000 --gaussians 20000 200000 1000000 --threads 1 2
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"
VIEW_FRAMES = tuple(range(0, 200, 10))
NEAR_FRAMES = tuple(range(0, 25, 5))  # --in-view: views (and the in-view map's points) from nearby frames


@functools.lru_cache(maxsize=None)
def _phases():
    """update_phases.py beside this file (the ideal loop, the ``--phases`` timer and table), however this one runs."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("update_phases", Path(__file__).with_name("update_phases.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def view_frames(in_view: int | None) -> tuple:
    return VIEW_FRAMES if in_view is None else NEAR_FRAMES


# ------------------------------------------------------------------------------------------------ worker side ----

def worker(threads: int, plys: list[str], warm: int, updates: int, data: str, in_view: int | None,
           phases: bool = False) -> None:
    # the package's public names before torch, numba or Open3D, as the eligsir command and a user's script load
    # them: each checkout runs with its own process set-up (OpenMP's wait policy, numba's threading layer)
    from eligsir_o3d import Config, Reconstructor
    from eligsir_o3d.datasets import open_sequence
    import numba
    import numpy as np
    import torch

    def set_threads(n: int) -> None:
        torch.set_num_threads(n)
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))

    set_threads(threads)

    clock = time.process_time if threads == 1 else time.perf_counter
    seq = open_sequence(data)
    cfg = Config(renderer="cpu")
    rec = Reconstructor(seq.camera, "cpu", cfg)
    for i in view_frames(in_view):
        (getattr(rec.views, "retain", None) or rec.views._admit)(seq.frame(i, depth_max=rec.config.depth_max))
    rec.warmup()
    probe = _phases().ideal_loop()
    timing = _phases().phase_timer(rec) if phases else None

    def phases_since():  # --phases: the seconds per phase since the last call (None without --phases)
        out = None if timing is None else dict(timing.seconds)
        if timing is not None:
            timing.seconds.clear()
        return out

    import eligsir_o3d
    print(json.dumps({"info": {"package": str(Path(eligsir_o3d.__file__).parent), "threads": threads,
                               "views": len(rec.views.views), "numba_layer": numba.threading_layer(),
                               "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY")}}), flush=True)
    for _line in sys.stdin:
        rows = []
        for ply in plys:
            rec.load_ply(ply)
            rec.rng.manual_seed(0)
            n0 = len(rec.gmap)
            rec.optimize(warm, scale=0.25)
            ts, ts1, seen = [], [], []
            phases_since()  # the warm-up's out
            phase_s1 = None
            for _ in range(updates):
                t0 = clock()
                rec.optimize(1, scale=0.25)
                ts.append(clock() - t0)
                seen.append(getattr(rec, "last_in_view", None) or len(rec.gmap))
            phase_s = phases_since()
            if threads > 1:  # the paired sample: as many updates on one thread next (after one untimed), wall clock
                set_threads(1)
                rec.optimize(1, scale=0.25)
                phases_since()
                for _ in range(updates):
                    t0 = clock()
                    rec.optimize(1, scale=0.25)
                    ts1.append(clock() - t0)
                phase_s1 = phases_since()
                set_threads(threads)
            rows.append({"gaussians": n0, "gaussians_end": len(rec.gmap), "seconds": ts, "in_view": seen,
                         "seconds_1": ts1, "phases": phase_s, "phases_1": phase_s1})
        print(json.dumps({"rows": rows, "ideal": _phases().ideal_speedup(probe, threads)}), flush=True)


# ------------------------------------------------------------------------------------------------ driver side ----

def _out_of_view(pts, cols, n: int, frames, seed: int):
    """``n`` copies of kitchen points (and their colours) shifted by 30-90 m, none of them reachable from a view."""
    import numpy as np
    import torch

    from eligsir_o3d.render.culling import in_view

    g = torch.Generator().manual_seed(seed + 1)
    shifts = torch.tensor([[x, y, z] for x in (-60, 0, 60) for y in (-60, 0, 60) for z in (-60, 0, 60)
                           if (x, y, z) != (0, 0, 0)], dtype=torch.float32)
    got_p, got_c, have = [pts[:0]], [cols[:0]], 0  # n = 0 (every map the size of the in-view part): none
    while have < n:
        sel = torch.randint(0, pts.shape[0], (n - have + 1024,), generator=g)
        p = pts[sel] + shifts[torch.randint(0, len(shifts), (sel.numel(),), generator=g)]
        keep = torch.ones(sel.numel(), dtype=torch.bool)
        logs = torch.full_like(p, float(np.log(0.05)))  # the largest scale a map Gaussian gets here
        for f in frames:
            keep[in_view(p, logs, f.camera, f.T_world_cam)] = False
        got_p.append(p[keep])
        got_c.append(cols[sel][keep])
        have += int(keep.sum())
    return torch.cat(got_p)[:n], torch.cat(got_c)[:n]


def write_maps(sizes: list[int], out: Path, data: Path, seed: int = 0, in_view: int | None = None) -> list[Path]:
    """One PLY per size: kitchen depth back-projected (frames of VIEW_FRAMES), ``n`` points at random; with
    ``in_view``, those ``in_view`` points plus ``n - in_view`` out of every view (:func:`_out_of_view`)."""
    import numpy as np
    import open3d as o3d
    import torch

    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.core.gaussians import GaussianMap
    from eligsir_o3d.io.ply import save_ply

    seq = open_sequence(data)
    pts, cols = [], []
    for i in view_frames(in_view):
        f = seq.frame(i)
        p, idx = f.camera.backproject(torch.as_tensor(f.depth).cpu().float())
        T = torch.as_tensor(np.asarray(f.T_world_cam), dtype=torch.float32)
        pts.append(p @ T[:3, :3].T + T[:3, 3])
        cols.append(torch.as_tensor(f.color).cpu().float().reshape(-1, 3)[idx])
    pts, cols = torch.cat(pts), torch.cat(cols)
    paths = []
    far = None
    if in_view is not None:
        far = _out_of_view(pts, cols, max(sizes) - in_view, [seq.frame(i) for i in view_frames(in_view)], seed)
    for n in sizes:
        g = torch.Generator().manual_seed(seed)
        sel = torch.randperm(pts.shape[0], generator=g)[:n if in_view is None else in_view]
        p, c = pts[sel].contiguous(), cols[sel].contiguous()
        if far is not None:
            p, c = torch.cat([p, far[0][:n - in_view]]), torch.cat([c, far[1][:n - in_view]])
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.double().numpy()))
        nn = torch.from_numpy(np.asarray(pcd.compute_nearest_neighbor_distance())).float().clamp(1e-3, 0.05)
        gm = GaussianMap(0)
        gm.add(p, c, nn, 0.5, torch.nn.functional.normalize(torch.randn(p.shape[0], 4, generator=g), dim=-1))
        paths.append(save_ply(gm, out / f"map_{n}.ply"))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--code", action="append", default=[], metavar="NAME=DIR",
                    help="a checkout to time (repeatable; default: this one as 'this'); the first is the baseline")
    ap.add_argument("--gaussians", type=int, nargs="+", default=[5000, 20000])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2,
                    help="worker processes per checkout and thread count, pooled (a process's speed varies by a "
                         "few per cent from one start to the next)")
    ap.add_argument("--updates", type=int, default=5, help="timed updates per map per round")
    ap.add_argument("--warm", type=int, default=2, help="untimed updates after each reload")
    ap.add_argument("--in-view", type=int, help="every map holds this many Gaussians in view, the rest out of view")
    ap.add_argument("--maps", type=Path, nargs="+", help="time these 3DGS PLYs (e.g. mapped maps) instead")
    ap.add_argument("--data", type=Path, default=KITCHEN)
    ap.add_argument("--phases", action="store_true",
                    help="also time the phases of the updates (view test, render, loss, backward, Adam, MCMC, ...) "
                         "and report each one's speed-up from 1 thread, paired as the whole updates are")
    ap.add_argument("--json", type=Path, help="write every timed update here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--plys", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.threads[0], args.plys, args.warm, args.updates, str(args.data), args.in_view, args.phases)
        return 0
    codes = [c.partition("=") for c in args.code] or [("this", "=", str(ROOT))]
    for name, eq, d in codes:
        if not eq or not (Path(d) / "eligsir_o3d").is_dir():
            ap.error(f"--code {name}{eq}{d}: expected NAME=DIR with DIR/eligsir_o3d")
    tmp = tempfile.TemporaryDirectory(prefix="update_time_")
    if args.in_view is not None and not args.maps and min(args.gaussians) < args.in_view:
        ap.error(f"--in-view {args.in_view}: every --gaussians size must be at least that")
    plys = args.maps or write_maps(args.gaussians, Path(tmp.name), args.data, in_view=args.in_view)
    results = run_rounds(start_workers(codes, args, plys), args.rounds)
    table = report(results, codes, args.threads)
    if args.phases:
        _phases().report_phases(results, codes, args.threads)
    if args.json:
        args.json.write_text(json.dumps({"median_ms": table, "rounds": {f"{k[0]}@{k[1]}": v
                                                                         for k, v in results.items()}}) + "\n")
    tmp.cleanup()
    return 0


def start_workers(codes, args, plys) -> dict:
    """``--workers`` worker processes per (checkout, thread count), started and waited for (their info lines
    printed)."""
    procs = {}
    for name, _, d in codes:
        for th, i in ((th, i) for th in args.threads for i in range(args.workers)):
            env = dict(os.environ, PYTHONPATH=str(Path(d).resolve()))
            cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--threads", str(th), "--warm",
                   str(args.warm), "--updates", str(args.updates), "--data", str(args.data),
                   *(["--in-view", str(args.in_view)] if args.in_view is not None else []),
                   *(["--phases"] if args.phases else []),
                   "--plys", *map(str, plys)]
            procs[(name, th, i)] = subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                                 text=True, cwd=str(ROOT))
    for key, p in procs.items():
        line = p.stdout.readline()
        if not line:
            raise SystemExit(f"worker {key} failed to start")
        print(f"# {key[0]} ({key[1]} thread(s), worker {key[2]}): {json.loads(line)['info']}")
    return procs


def run_rounds(procs: dict, rounds: int) -> dict:
    """The workers take turns, round after round; returns {(checkout, threads): [rows of each round and worker]}."""
    policy = os.environ.get("OMP_WAIT_POLICY", "each checkout's own default")
    print(f"# OMP_WAIT_POLICY {policy}")
    print(f"# loadavg at start {' '.join(open('/proc/loadavg').read().split()[:3])}")
    results = {k[:2]: [] for k in procs}
    ideal = {}
    for _ in range(rounds):
        for key, p in procs.items():
            p.stdin.write("go\n")
            p.stdin.flush()
            answer = json.loads(p.stdout.readline())
            results[key[:2]].append(answer["rows"])
            ideal.setdefault(key[:2], []).append(answer["ideal"])
    for p in procs.values():
        p.stdin.close()
        p.wait()
    print(f"# loadavg at end {' '.join(open('/proc/loadavg').read().split()[:3])}")
    for (name, th), sp in ideal.items():
        if th > 1:
            sp = sorted(sp)
            print(f"# {name}, {th} threads: an ideal parallel loop timed in each round ran {sp[len(sp) // 2]:.2f}x "
                  f"faster than on 1 thread (rounds {sp[0]:.2f}-{sp[-1]:.2f}): what the machine's threads gave")
    return results


def report(results: dict, codes, threads) -> dict:
    """Print the table (median ms per update, ratios to the first checkout, size and thread ratios); returns
    {"<threads>x<gaussians>": {checkout: median ms}}."""
    import numpy as np
    print(f"{'threads':>7} {'gaussians':>9} " + " ".join(f"{n + ' ms':>12}" for n, _, _ in codes)
          + "".join(f" {codes[0][0] + '/' + n:>14}" for n, _, _ in codes[1:]) + "   (N at end per code)")
    table = {}
    for th in threads:
        for gi, n in enumerate([r["gaussians"] for r in results[(codes[0][0], th)][0]]):
            med, ends, seen = [], [], []
            for name, _, _ in codes:
                rows = [r[gi] for r in results[(name, th)]]
                med.append(1e3 * float(np.median([t for row in rows for t in row["seconds"]])))
                ends.append(max(row["gaussians_end"] for row in rows))
                seen.append(int(np.median([v for row in rows for v in row.get("in_view", [row["gaussians"]])])))
            table[f"{th}x{n}"] = dict(zip([c[0] for c in codes], med))
            print(f"{th:>7} {n:>9} " + " ".join(f"{m:12.1f}" for m in med)
                  + "".join(f" {med[0] / m:14.2f}" for m in med[1:]) + f"   {ends} in view {seen}")
    sizes = [r["gaussians"] for r in results[(codes[0][0], threads[0])][0]]
    for name, _, _ in codes:
        for th in threads:
            ms = [table[f"{th}x{n}"][name] for n in sizes]
            print(f"# {name}, {th} thread(s): time / time at {sizes[0]} Gaussians: "
                  + " ".join(f"{n}: {m / ms[0]:.2f}" for n, m in zip(sizes, ms)))
        for th in (t for t in threads if t > 1):
            paired = [[float(np.median(r[gi]["seconds_1"]) / np.median(r[gi]["seconds"]))
                       for r in results[(name, th)] if r[gi]["seconds_1"]] for gi in range(len(sizes))]
            if all(paired):
                print(f"# {name}: speed-up of {th} over 1 thread, paired (each round's updates on {th} threads "
                      "followed by as many on 1 thread in the same process, wall clock; median over rounds of the "
                      "ratio of their medians) " + "/".join(f"{float(np.median(p)):.2f}" for p in paired))
        if len(threads) > 1:
            t0 = threads[0]
            print(f"# {name}: speed-up of " + ", ".join(
                f"{th} over {t0} thread(s) " + "/".join(f"{table[f'{t0}x{n}'][name] / table[f'{th}x{n}'][name]:.2f}"
                                                        for n in sizes) for th in threads[1:]))
    return table


if __name__ == "__main__":
    sys.exit(main())
