"""Two 1-CPU batch tasks side by side vs one after the other, on a local Ray (eligsir_o3d.batch.map_many).

    python benchmarks/platforms/batch_parallel.py [--frames 32] [--reps 3] [--out /tmp/batch_parallel]

Each rep maps the same two sequences (the first --frames frames of 7-Scenes and of SUN3D, the fixed-updates
budget, so the work does not depend on load) three ways, in alternating order within one process:
  serial-1t   a local Ray with 1 CPU: the two 1-thread tasks run one after the other
  serial-2t   a local Ray with 2 CPUs, 2 CPUs per task: one after the other, 2 threads each
  parallel    a local Ray with 2 CPUs, 1 CPU per task: both at once, 1 thread each
and prints the wall time of each (Ray start excluded, worker start included) with the load average around it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import ray

from eligsir_o3d.batch import map_many

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"


def one(mode: str, frames: int, out: Path, cfg: Path) -> dict:
    cpus_total, per_task = {"serial-1t": (1, 1), "serial-2t": (2, 2), "parallel": (2, 1)}[mode]
    ray.init(num_cpus=cpus_total, include_dashboard=False, object_store_memory=100 * 2**20, log_to_driver=False,
             logging_level="WARNING")
    try:
        shutil.rmtree(out, ignore_errors=True)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        res = map_many([str(DATA / "7scenes_redkitchen_jpg1000"), str(DATA / "sun3d_mit76_studyroom_f0935")], out,
                       max_frames=frames, config=str(cfg), eval_every=0, plots=False, checkpoint_every=0,
                       cpus_per_task=per_task, echo=None)
        wall = time.perf_counter() - t0
    finally:
        ray.shutdown()
    assert all(r.status == "done" for r in res), [(r.name, r.error) for r in res]
    return {"mode": mode, "wall_s": wall, "load_before": load0, "load_after": os.getloadavg()[0],
            "mapping_s": [r.metrics["mapping_time_s"] for r in res], "psnr": [r.metrics["heldout"]["psnr"] for r in res],
            "peak_rss_mb": [r.metrics["peak_rss_mb"] for r in res]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("/tmp/batch_parallel"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    cfg = a.out / "updates.json"
    cfg.write_text(json.dumps({"clock": {"mode": "updates", "updates_per_frame": 8}}))
    rows = []
    for rep in range(a.reps):
        order = ["serial-1t", "parallel", "serial-2t"] if rep % 2 == 0 else ["parallel", "serial-2t", "serial-1t"]
        for mode in order:
            r = one(mode, a.frames, a.out / mode, cfg)
            r["rep"] = rep
            rows.append(r)
            print(json.dumps(r), flush=True)
    for mode in ("serial-1t", "serial-2t", "parallel"):
        w = sorted(r["wall_s"] for r in rows if r["mode"] == mode)
        print(f"{mode:10s} wall s: {', '.join(f'{x:.1f}' for x in w)} (median {w[len(w) // 2]:.1f})")
    for rep in range(a.reps):
        by = {r["mode"]: r["wall_s"] for r in rows if r["rep"] == rep}
        print(f"rep {rep}: serial-1t / parallel = {by['serial-1t'] / by['parallel']:.2f}, "
              f"serial-2t / parallel = {by['serial-2t'] / by['parallel']:.2f}")


if __name__ == "__main__":
    main()
