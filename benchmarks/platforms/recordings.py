"""Same frames, other containers: map the first N frames of 7-Scenes from the folder and from bags / a .sens.

Writes the first ``--frames`` frames of ``../shared/data/7scenes_redkitchen_jpg1000`` (ground-truth poses on a
pose topic) as a RealSense-layout bag (when Open3D reads it back), a ROS 1 bag, ROS 2 bags (sqlite3 and mcap) and a
ScanNet ``.sens``, runs ``eligsir map`` (deterministic budget clock, ground-truth poses, every 8th frame held out)
on each and on the folder, and prints the held-out PSNR of each against the folder's.

    python benchmarks/platforms/recordings.py --frames 200 --work /tmp/recordings
    python benchmarks/platforms/recordings.py --rss 1000     # peak RSS reading 100 vs 1000 frames of a bag (subprocesses)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SEVEN = ROOT / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"


def write_all(frames: int, work: Path) -> dict[str, Path]:
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.datasets.writers import write_realsense_bag, write_rosbag, write_sens

    src = open_sequence(SEVEN)
    work.mkdir(parents=True, exist_ok=True)
    out = {"ros1": work / "ros1.bag", "ros2-sqlite3": work / "ros2_sqlite3", "ros2-mcap": work / "ros2_mcap",
           "scannet": work / "scene.sens"}
    for p in out.values():
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
    write_rosbag(src, out["ros1"], ros=1, frames=range(frames))
    write_rosbag(src, out["ros2-sqlite3"], ros=2, storage="sqlite3", frames=range(frames))
    write_rosbag(src, out["ros2-mcap"], ros=2, storage="mcap", frames=range(frames))
    write_sens(src, out["scannet"], frames=range(frames))
    out["realsense"] = work / "realsense.bag"
    out["realsense"].unlink(missing_ok=True)
    write_realsense_bag(src, out["realsense"], frames=range(frames), poses=True)
    return out


def map_psnr(path: Path, frames: int, out: Path) -> float:
    cmd = [sys.executable, "-c", "from eligsir_o3d.cli.app import main; main()", "map", str(path), "--out", str(out),
           "--max-frames", str(frames), "-q"]
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL)
    return json.loads((out / "metrics.json").read_text())["heldout"]["psnr"]


def peak_rss_reading(path: Path, n: int) -> float:
    """Peak RSS (MB) of a fresh process that opens ``path`` and reads its first n frames."""
    code = (f"from eligsir_o3d.datasets import open_sequence; import resource\n"
            f"s = open_sequence({str(path)!r})\n"
            f"for i in range({n}): s.frame(i)\n"
            f"print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)")
    r = subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    return float(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--work", type=Path, default=Path("/tmp/eligsir_recordings"))
    ap.add_argument("--rss", type=int, default=0, help="measure peak RSS reading 100 vs this many bag frames")
    ap.add_argument("--only", nargs="*", help="containers to map (default: all)")
    a = ap.parse_args()
    if a.rss:
        from eligsir_o3d.datasets import open_sequence
        from eligsir_o3d.datasets.writers import write_rosbag

        bag = a.work / f"rss_{a.rss}.bag"
        a.work.mkdir(parents=True, exist_ok=True)
        if not bag.is_file():
            write_rosbag(open_sequence(SEVEN), bag, ros=1, frames=range(a.rss), color="jpeg")
        small, big = peak_rss_reading(bag, 100), peak_rss_reading(bag, a.rss)
        print(f"bag {bag} ({bag.stat().st_size / 1e6:.0f} MB): peak RSS reading 100 frames {small:.0f} MB, "
              f"{a.rss} frames {big:.0f} MB, ratio {big / small:.3f}")
        return
    paths = write_all(a.frames, a.work)
    ref = map_psnr(SEVEN, a.frames, a.work / "run_folder")
    print(f"folder: held-out PSNR {ref:.3f} dB")
    for name, p in paths.items():
        if a.only and name not in a.only:
            continue
        psnr = map_psnr(p, a.frames, a.work / f"run_{name}")
        print(f"{name}: held-out PSNR {psnr:.3f} dB (folder {ref:.3f}, difference {psnr - ref:+.3f} dB)", flush=True)
    print(f"peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
