"""Every script in examples/ runs on a few real frames (in this process, through runpy, with tiny budgets)."""

from __future__ import annotations

import json
import runpy
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SEVEN = ROOT / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


def run_example(name: str, *args: str, capsys) -> str:
    argv = sys.argv
    sys.argv = [str(EXAMPLES / name), *map(str, args)]
    try:
        runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    finally:
        sys.argv = argv
    return capsys.readouterr().out


def test_every_example_has_a_test():
    here = Path(__file__).read_text()
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert scripts == sorted(["integrate_loop.py", "own_capture.py", "bag_to_ply.py", "custom_pose_source.py",
                              "export_mesh.py"])
    assert all(f'"{s}"' in here for s in scripts)


def test_integrate_loop_then_export_mesh(tmp_path, capsys, monkeypatch):
    out = run_example("integrate_loop.py", SEVEN, "--frames", 6, "--updates", 2, "--drain", 5, "--out", tmp_path, capsys=capsys)
    assert "Gaussians" in out and (tmp_path / "map.ply").is_file()
    from eligsir_o3d.io.ply import load_ply

    assert len(load_ply(tmp_path / "map.ply")) > 100
    # export_mesh needs viewpoints: the loop wrote no trajectory.txt, so give it the frames' poses
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.pose import write_tum_trajectory

    seq = open_sequence(SEVEN)
    write_tum_trajectory(tmp_path / "trajectory.txt", seq.timestamps[:6], seq.poses[:6])
    monkeypatch.setenv("DISPLAY", "")
    out = run_example("export_mesh.py", tmp_path / "map.ply", "--max-views", 6, "--voxel-size", 0.04,
                      capsys=capsys)
    assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "cloud.ply").is_file()
    n_tri = int(out.split(" triangles;")[0].rsplit(" ", 1)[-1])
    assert n_tri > 100, out


def test_own_capture_tracks_a_folder_without_poses(tmp_path, capsys):
    cap = tmp_path / "capture"
    (cap / "color").mkdir(parents=True)
    (cap / "depth").mkdir()
    for i in range(6):
        shutil.copy(SEVEN / "rgb" / f"{i:06d}.jpg", cap / "color")
        shutil.copy(SEVEN / "depth" / f"{i:06d}.png", cap / "depth")
    intr = json.loads((SEVEN / "intrinsics.json").read_text())
    (cap / "intrinsics.json").write_text(json.dumps({k: intr[k] for k in
                                                     ("width", "height", "fx", "fy", "cx", "cy", "depth_scale")}))
    out = run_example("own_capture.py", cap, "--updates", 1, "--drain", 5, "--out", tmp_path / "run", capsys=capsys)
    assert "tracked 6 frames" in out, out
    lines = [ln for ln in (tmp_path / "run" / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 6
    last = np.array(lines[-1].split()[1:4], dtype=float)
    assert 0.0 < np.linalg.norm(last) < 0.2  # the camera moved a little over 6 frames (0.2 s)


def test_bag_to_ply_from_a_ros_bag(tmp_path, capsys):
    pytest.importorskip("rosbags")
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.datasets.writers import write_rosbag

    bag = write_rosbag(open_sequence(SEVEN), tmp_path / "cap.bag", ros=1, frames=range(5))
    out = run_example("bag_to_ply.py", bag, "--updates", 2, "--drain", 5, "--out", tmp_path / "run", capsys=capsys)
    assert (tmp_path / "run" / "map.ply").is_file() and (tmp_path / "run" / "mesh.ply").is_file()
    assert "format='ros1'" in out and "poses=yes" in out
    assert int(out.split("mesh with ")[1].split()[0]) > 100, out


def test_custom_pose_source_tracks_close_to_ground_truth(capsys):
    out = run_example("custom_pose_source.py", SEVEN, "--frames", 8, "--updates", 1, "--drain", 5, capsys=capsys)
    assert "constant-velocity odometry: 8 frames" in out, out
    ate_cm = float(out.split("ATE against the sequence's poses: ")[1].split()[0])
    assert ate_cm < 2.0, out
