"""Held-out views of tracked runs side by side: the recording's image beside each run's render, with its PSNR.

For two (or more) results folders of one recording mapped without poses (e.g. loop closure off and on), each
run's map is rendered at the held-out frames' ground-truth poses moved into that run's frame by one rigid
alignment of its ``trajectory.txt`` to the ground truth (the paper's rule, as the run's own evaluation does). The
frames are chosen from ``--from``..``--to`` (default: the last third of the run, where the kitchen's walk
revisits its start) and written as one PNG row per frame; the per-frame PSNRs are printed and saved as JSON.

    python -m benchmarks.quality.loops_picture runs/odo700_off runs/odo700_on --names off on --out runs/loops_pic
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from eligsir_o3d import Reconstructor
from eligsir_o3d.core.camera import invert_pose
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.eval.metrics import psnr
from eligsir_o3d.pose import read_tum_trajectory
from eligsir_o3d.pose.accuracy import pose_alignment


def aligned_poses(run: Path, seq) -> dict[int, np.ndarray]:
    """Sequence index -> ground-truth pose in the run's map frame (one rigid alignment of trajectory.txt)."""
    stamps, est = read_tum_trajectory(run / "trajectory.txt")
    index = {round(float(t), 4): i for i, t in enumerate(seq.timestamps)}
    pairs = [(index[round(float(t), 4)], T) for t, T in zip(stamps, est) if round(float(t), 4) in index]
    A = pose_alignment([T for _, T in pairs], [seq.poses[i] for i, _ in pairs])  # T_gt_est
    return {i: invert_pose(A) @ seq.poses[i] for i in range(len(seq.timestamps))}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--names", nargs="+")
    ap.add_argument("--sequence", type=Path)
    ap.add_argument("--from", dest="start", type=float, default=2 / 3, help="share of the run's frames to start at")
    ap.add_argument("--to", dest="stop", type=float, default=1.0)
    ap.add_argument("--frames", type=int, default=3, help="held-out frames shown (evenly spread)")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    names = a.names or [r.name for r in a.runs]
    metrics = [json.loads((r / "metrics.json").read_text()) for r in a.runs]
    seq = open_sequence(a.sequence or metrics[0]["dataset"])
    held = [v["index"] for v in metrics[0]["per_view"]]
    n = metrics[0]["frames_total"]
    chosen = [i for i in held if a.start * n <= i < a.stop * n]
    chosen = [chosen[int(k)] for k in np.linspace(0, len(chosen) - 1, min(a.frames, len(chosen)))]
    rows, table = [], {}
    for i in chosen:
        frame = seq.frame(i)
        gt = frame.at_scale(a.scale)[0].numpy()
        row = [gt]
        for run, name in zip(a.runs, names):
            rec = Reconstructor(seq.camera, "cpu")
            rec.load_ply(run / "map.ply")
            img = rec.render(aligned_poses(run, seq)[i], scale=a.scale).color.numpy()
            table.setdefault(name, {})[i] = round(float(psnr(img, gt)), 2)
            row.append(img)
        rows.append(np.concatenate(row, 1))
    import cv2

    a.out.mkdir(parents=True, exist_ok=True)
    picture = (np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8)[..., ::-1]
    cv2.imwrite(str(a.out / "heldout_side_by_side.png"), picture)
    (a.out / "heldout_side_by_side.json").write_text(json.dumps({"columns": ["recording", *names], "psnr": table}))
    print(f"columns: recording | {' | '.join(names)}; frames {chosen}")
    for name in names:
        print(name, table[name])


if __name__ == "__main__":
    main()
