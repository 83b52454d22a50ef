"""Does pose refinement help where the truth is known? (issue 32, item 4)

The synthetic room is rendered at known poses. The mapper is given those poses with a known error added (each
source frame independently: a rotation of ``--rot-deg`` degrees about a random axis and a translation of
``--trans-mm`` millimetres in a random direction, seeded), through a TUM trajectory file (``--pose PATH``), and the
held-out views are scored at their TRUE poses after one rigid alignment of the mapped (refined) training poses to
the truth: the paper's rule, at the true poses. Refinement on and off, side by side, for each seed; the same run
with the exact poses is the ceiling.

    python benchmarks/quality/pose_truth.py                       # 60 frames at 320x240, refinement on/off, seeds 0 1
    python benchmarks/quality/pose_truth.py --frames 40 --seeds 0 --rot-deg 0.5 --trans-mm 10 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def perturbed_poses(poses: list[np.ndarray], rot_deg: float, trans_mm: float, seed: int) -> list[np.ndarray]:
    """Each camera-to-world pose [4, 4] with an independent error: T @ [exp(rot_deg about a random axis) |
    trans_mm in a random direction] (camera frame), both of exactly the given size."""
    from eligsir_o3d.pose.refine import _rot_exp

    rng = np.random.default_rng(seed)
    out = []
    for T in poses:
        a = rng.normal(size=3)
        t = rng.normal(size=3)
        D = np.eye(4)
        D[:3, :3] = _rot_exp(a / np.linalg.norm(a) * np.radians(rot_deg))
        D[:3, 3] = t / np.linalg.norm(t) * trans_mm * 1e-3
        out.append(np.asarray(T, dtype=np.float64) @ D)
    return out


def run_one(out: Path, frames: int, size: tuple[int, int], refine: bool, pose_file: str | None, seed: int,
            speed: float) -> dict:
    """One mapping of the synthetic room; returns the held-out PSNR (true poses, rigid training alignment)."""
    from eligsir_o3d import Config
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    cfg = Config(seed=seed)
    cfg.pose_refine.enabled = refine
    cfg.clock.speed = speed
    opts = RunOptions(max_frames=frames, sequence_options={"n_frames": frames, "width": size[0], "height": size[1]},
                      pose=pose_file or "gt", eval_every=0, progress=False, plots=False, pictures=False)
    m = run_mapping("synthetic", out, cfg, opts)
    rules = m.get("heldout_by_pose_rule") or {}
    return {"psnr": m["heldout"]["psnr"], "ate_mm": None if m["ate_rmse_m"] is None else 1e3 * m["ate_rmse_m"],
            "gaussians": m["gaussians"], "updates": m["updates"], "pose_refine": m.get("pose_refine"),
            **({f"psnr_{r}": v["psnr"] for r, v in rules.items()})}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", type=int, nargs=2, default=(320, 240))
    ap.add_argument("--rot-deg", type=float, default=0.3)
    ap.add_argument("--trans-mm", type=float, default=5.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--out", default=None, help="keep the results folders here (default: a temporary folder)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.pose import write_tum_trajectory

    base = Path(a.out or tempfile.mkdtemp(prefix="pose_truth_"))
    base.mkdir(parents=True, exist_ok=True)
    seq = open_sequence("synthetic", n_frames=a.frames, width=a.size[0], height=a.size[1])
    rows = []
    for seed in a.seeds:
        traj = base / f"noisy_seed{seed}.txt"
        write_tum_trajectory(traj, seq.timestamps, perturbed_poses(seq.poses, a.rot_deg, a.trans_mm, seed))
        for name, refine, pose in (("noisy, refinement on", True, str(traj)),
                                   ("noisy, refinement off", False, str(traj)),
                                   ("exact poses, refinement off", False, None)):
            r = run_one(base / f"{name.replace(', ', '_').replace(' ', '-')}_seed{seed}", a.frames,
                        tuple(a.size), refine, pose, seed, a.speed)
            rows.append({"seed": seed, "run": name, **r})
            if not a.json:
                print(f"seed {seed}  {name:28s}  held-out PSNR at the true poses {r['psnr']:6.2f} dB  "
                      f"ATE {r['ate_mm'] if r['ate_mm'] is None else round(r['ate_mm'], 2)} mm  "
                      f"{r['gaussians']} Gaussians  {r['updates']} updates", flush=True)
    if a.json:
        print(json.dumps({"frames": a.frames, "size": a.size, "rot_deg": a.rot_deg, "trans_mm": a.trans_mm,
                          "rows": rows}, indent=1))
    else:
        for name in dict.fromkeys(r["run"] for r in rows):
            v = [r["psnr"] for r in rows if r["run"] == name]
            print(f"mean over seeds  {name:28s}  {np.mean(v):6.2f} dB  (seeds: {', '.join(f'{x:.2f}' for x in v)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
