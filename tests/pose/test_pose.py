"""Pose sources: trajectory files, accuracy (Umeyama, ATE/RPE), Open3D odometry, kiss-icp, pycolmap.

Tolerances (stated, measured on the synthetic room at 160x120, 1.2 cm and ~0.5 deg between frames):
- Open3D odometry over 20 frames, rotation error < 1 deg throughout: frame-to-model ATE < 1.5 cm (measured 0.9 cm:
  a 2 cm-voxel TSDF of 160x120 frames is coarse at 3-4 m); frame-to-frame point-to-plane < 1 cm (measured 0.4 cm);
  frame-to-frame Hybrid at 320x240 over 12 frames < 1.2 cm (measured 0.6 cm; at 160x120 its photometric term
  drifts 0.3 deg per frame on this texture). On real 7-Scenes frames frame-to-model is the most accurate
  (benchmarks/quality/poses.py).
- kiss-icp drifts ~1 cm per frame on this planar, narrow-field-of-view room (point-to-point ICP slides along the
  walls), so it is tested on 30 real 7-Scenes frames instead: ATE < 2 cm (measured ~0.6 cm); skipped without the data.
- pycolmap on 10 real SUN3D frames (every 5th, 640x480, ~5 s): all registered, ATE < 3 cm (measured 1.6-1.8 cm
  over three runs), metric scale within 10 % of the ground truth's (measured 4-7 %; SUN3D's own poses come from a
  reconstruction). Not on the synthetic room: its smooth procedural textures give ~300 SIFT points at 320x240
  and about one SfM run in five breaks after a few frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c
import pytest
import torch

from eligsir_o3d.core.camera import Camera, invert_pose, rotation_angle_deg
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.pose import (PoseSource, TrackingLost, get_pose_source, plot_trajectories, read_tum_trajectory,
                              trajectory_accuracy, umeyama_alignment, write_tum_trajectory)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
KITCHEN = DATA / "7scenes_redkitchen_jpg1000"
STUDYROOM = DATA / "sun3d_mit76_studyroom_f0935"


def random_pose(rng, t_scale=1.0) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = rng.normal(size=3) * t_scale
    return T


@pytest.fixture(scope="module")
def room():
    """The synthetic room, 720 frames per loop (1.2 cm between frames), 160x120."""
    return open_sequence("synthetic", n_frames=720, width=160, height=120)


@pytest.fixture(scope="module")
def room_vga_half():
    """The same room at 320x240 (the Hybrid photometric term needs more than 160x120 of this texture)."""
    return open_sequence("synthetic", n_frames=720, width=320, height=240)


def run_source(src: PoseSource, seq, n: int, start: int = 0) -> list[np.ndarray]:
    src.prepare(seq)
    poses = []
    for i in range(start, start + n):
        f = seq.frame(i)
        poses.append(src.track(i, f.timestamp, f.color, f.depth, f.camera,
                               gt_pose=seq.poses[i] if i == start else None))
    return poses


# -- trajectory files -------------------------------------------------------------------------------------------------
def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.01, 0.05, 20)) + 1e3
    poses = [random_pose(rng) for _ in stamps]
    path = write_tum_trajectory(tmp_path / "sub" / "traj.txt", stamps, poses)
    ts, ps = read_tum_trajectory(path)
    np.testing.assert_allclose(ts, stamps, atol=1e-6)
    for a, b in zip(ps, poses):
        np.testing.assert_allclose(a, b, atol=1e-8)


def test_tum_read_errors(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("# header\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad.txt:3: expected 8 fields"):
        read_tum_trajectory(p)
    p.write_text("0.0 0 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="zero quaternion"):
        read_tum_trajectory(p)
    with pytest.raises(FileNotFoundError):
        read_tum_trajectory(tmp_path / "missing.txt")


def test_trajectory_file_source_matches_by_timestamp(tmp_path):
    rng = np.random.default_rng(1)
    stamps = np.arange(10) / 30.0
    poses = [random_pose(rng) for _ in stamps]
    path = write_tum_trajectory(tmp_path / "t.txt", stamps, poses)
    src = get_pose_source(str(path), max_diff=0.01)
    assert src.causal and src.name.startswith("file:")
    np.testing.assert_allclose(src.track(3, stamps[3] + 0.004, None, None, None), poses[3], atol=1e-8)
    with pytest.raises(TrackingLost, match=r"^frame 11: .*no pose within 0.01 s"):
        src.track(11, 11 / 30.0, None, None, None)


def test_gt_source_and_spec_errors(room, tmp_path):
    src = get_pose_source("gt", sequence=room)
    src.prepare()
    f = room.frame(5)
    np.testing.assert_allclose(src.track(5, f.timestamp, f.color, f.depth, f.camera), room.poses[5])
    np.testing.assert_allclose(src.track(5, f.timestamp, f.color, f.depth, f.camera, gt_pose=room.poses[7]),
                               room.poses[7])
    with pytest.raises(ValueError, match="unknown pose source 'nope'"):
        get_pose_source("nope")
    with pytest.raises(ValueError, match="no COLMAP model"):
        get_pose_source(str(tmp_path))
    assert get_pose_source("colmap").causal is False


# -- accuracy ---------------------------------------------------------------------------------------------------------
def test_umeyama_recovers_known_transform():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(50, 3))
    A = random_pose(rng, 3.0)
    T, s = umeyama_alignment(X, X @ A[:3, :3].T + A[:3, 3])
    np.testing.assert_allclose(T, A, atol=1e-9)
    assert s == 1.0
    T, s = umeyama_alignment(X, 2.5 * X @ A[:3, :3].T + A[:3, 3], with_scale=True)
    np.testing.assert_allclose(T, A, atol=1e-9)
    assert s == pytest.approx(2.5)


def test_trajectory_accuracy_known_errors(tmp_path):
    rng = np.random.default_rng(3)
    stamps = np.arange(100) / 30.0
    t = np.linspace(0, 2 * np.pi, 100)
    gt = []
    for a in t:  # a helix, the camera yawing along it
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [np.cos(a), np.sin(a), 0.1 * a]
        gt.append(T)
    A = random_pose(rng, 2.0)  # the estimate lives in another frame: alignment must remove it
    est = {s + 0.003: A @ T for s, T in zip(stamps, gt)}
    acc = trajectory_accuracy(est, (stamps, gt))
    assert acc["n_matched"] == 100
    assert acc["ate_rmse_m"] < 1e-9 and acc["rpe_trans_m"] < 1e-9 and acc["rpe_rot_deg"] < 1e-4
    noise = rng.normal(size=(100, 3)) * 0.01
    noisy = []
    for T, n in zip(gt, noise):
        T = T.copy()
        T[:3, 3] += n
        noisy.append(T)
    acc = trajectory_accuracy((stamps, noisy), (stamps, gt))
    assert acc["ate_rmse_m"] == pytest.approx(np.sqrt((noise ** 2).sum(1).mean()), rel=0.1)
    with pytest.raises(ValueError, match="only 0 poses matched"):
        trajectory_accuracy((stamps + 5.0, gt), (stamps, gt))
    png = plot_trajectories(tmp_path / "traj.png", {"gt": (stamps, gt), "est": est}, reference="gt")
    assert png.stat().st_size > 1000


# -- Open3D odometry --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("options, n, ate_tol", [({}, 20, 0.015),
                                                 ({"mode": "frame", "method": "point_to_plane"}, 20, 0.01),
                                                 ({"mode": "frame"}, 12, 0.012)])
def test_odometry_recovers_synthetic_trajectory(room, room_vga_half, options, n, ate_tol):
    seq = room_vga_half if options.get("mode") == "frame" and "method" not in options else room
    src = get_pose_source("odometry", scale=1.0, **options)
    poses = run_source(src, seq, n)
    acc = trajectory_accuracy((seq.timestamps[:n], poses), (seq.timestamps[:n], seq.poses[:n]))
    assert acc["ate_rmse_m"] < ate_tol, acc
    np.testing.assert_allclose(poses[0], seq.poses[0])  # first frame anchored at the given gt pose
    worst_rot = max(rotation_angle_deg(P[:3, :3].T @ G[:3, :3]) for P, G in zip(poses, seq.poses))
    assert worst_rot < 1.0
    assert src.seconds > 0 and src.frames_tracked == n


def test_raycast_half_voxel_correction(room):
    """Open3D 0.20 ray-casts a VoxelBlockGrid half a voxel off; odometry.py shifts it back. If this fails after an
    Open3D upgrade, the bias is gone: remove the shift in OdometrySource.__init__."""
    src = get_pose_source("odometry", scale=1.0)
    f = room.frame(0)
    src.prepare(room)
    src.track(0, f.timestamp, f.color, f.depth, f.camera, gt_pose=room.poses[0])
    K = o3c.Tensor(f.camera.K)
    corrected = src._raycast(K, f.camera, room.poses[0]).as_tensor().numpy()[..., 0]
    src._raycast_shift = np.eye(4)
    raw = src._raycast(K, f.camera, room.poses[0]).as_tensor().numpy()[..., 0]
    true = f.depth.numpy()
    bias = [float(np.median((d - true)[(d > 0) & (true > 0)])) for d in (corrected, raw)]
    # corrected: +3.7 mm run alone, +4.3 mm once inside the full suite (Open3D's parallel integration); raw: -9.4 mm
    assert abs(bias[0]) < 0.25 * src.voxel_size, bias
    assert abs(bias[1]) > 0.005, f"Open3D's ray-cast bias seems fixed ({bias}); drop the half-voxel shift"


def test_pose_convention_by_reprojection(room):
    """Tracked poses are camera-to-world in OpenCV axes: frame 0's depth, moved by them, lands on frame 12's."""
    n = 13
    poses = run_source(get_pose_source("odometry", scale=1.0, mode="frame", method="point_to_plane"), room, n)
    f0, f1 = room.frame(0), room.frame(n - 1)
    cam: Camera = f0.camera

    def reprojection_error(T0, T1) -> float:
        pts, idx = cam.backproject(f0.depth)
        pw = pts.numpy() @ T0[:3, :3].T + T0[:3, 3]
        pc = (pw - T1[:3, 3]) @ T1[:3, :3]  # world -> camera 1 (inverse of camera-to-world)
        z = pc[:, 2]
        u = np.rint(pc[:, 0] / z * cam.fx + cam.cx).astype(int)
        v = np.rint(pc[:, 1] / z * cam.fy + cam.cy).astype(int)
        ok = (z > 0.1) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        d1 = f1.depth.numpy()[v[ok], u[ok]]
        return float(np.median(np.abs(d1[d1 > 0] - z[ok][d1 > 0])))

    assert reprojection_error(room.poses[0], room.poses[n - 1]) < 0.005  # the dataset agrees with Camera
    assert reprojection_error(poses[0], poses[-1]) < 0.01
    assert reprojection_error(invert_pose(poses[0]), invert_pose(poses[-1])) > 0.05  # the wrong convention


@pytest.mark.parametrize("spec, options", [("odometry", {"scale": 1.0}), ("odometry", {"scale": 1.0, "mode": "frame"}),
                                           ("kiss-icp", {"stride": 2})])
def test_lost_tracking_is_reported(room, spec, options):
    src = get_pose_source(spec, **options)
    run_source(src, room, 5)
    f = room.frame(5)
    with pytest.raises(TrackingLost, match=r"^frame 5: .*depth"):
        src.track(5, f.timestamp, f.color, torch.zeros_like(f.depth), f.camera)
    color, depth = room.render(room.poses[360])  # the other side of the room, looking the other way
    with pytest.raises(TrackingLost, match=r"^frame 5: "):
        src.track(5, f.timestamp, torch.from_numpy(color), torch.from_numpy(depth), f.camera)
    assert src.frames_lost == 2
    T = src.track(5, f.timestamp, f.color, f.depth, f.camera)  # the state survived: tracking goes on
    assert np.linalg.norm(T[:3, 3] - room.poses[5][:3, 3]) < 0.2


def test_odometry_model_stays_small(room):
    """Past max_blocks, TSDF blocks far from the camera are dropped; tracking goes on.

    Three 8-frame windows, compared by their median: Open3D's ray cast of a small model is not deterministic (the
    same grid cast twice differs on ~1 % of pixels), and one window in a few then ends 0.03-0.08 m off (measured
    2026-12-04, 5 windows x 4 processes; the full model: 0.016-0.041 m)."""
    err = {"full": [], "small": []}
    for start in (0, 60, 120):
        for name, kw in (("full", {}), ("small", {"max_blocks": 100, "keep_radius": 3.0})):
            src = get_pose_source("odometry", scale=1.0, **kw)
            last = run_source(src, room, 8, start)[-1]
            err[name].append(np.linalg.norm(last[:3, 3] - room.poses[start + 7][:3, 3]))
            if name == "small":
                assert src.model_blocks < blocks_full
            else:
                blocks_full = src.model_blocks
    assert np.median(err["small"]) < np.median(err["full"]) + 0.02, err


def test_odometry_pruned_blocks_leave_no_values_behind(room):
    """Open3D's hash map gives an erased block's buffer slot to the next new block as it was: pruning clears it."""
    src = get_pose_source("odometry", scale=1.0, max_blocks=100, keep_radius=3.0)
    run_source(src, room, 3)
    hashmap = src._vbg.hashmap()
    live = hashmap.active_buf_indices().to(o3c.int64).numpy()
    dead = np.setdiff1d(np.arange(hashmap.capacity()), live)
    assert len(dead) > 0
    for name in ("tsdf", "weight"):
        assert not np.asarray(src._vbg.attribute(name).numpy())[dead].any(), name


def test_odometry_input_errors(room):
    src = get_pose_source("odometry")
    f = room.frame(0)
    with pytest.raises(ValueError, match="camera is"):
        src.track(0, 0.0, f.color, f.depth[:10], f.camera)
    with pytest.raises(ValueError, match="scale must be 1/n"):
        get_pose_source("odometry", scale=0.3)


# -- kiss-icp ---------------------------------------------------------------------------------------------------------
@pytest.mark.skipif(not KITCHEN.is_dir(), reason="needs ../shared/data/7scenes_redkitchen_jpg1000")
def test_kiss_icp_on_real_frames():
    pytest.importorskip("kiss_icp")
    seq = open_sequence(KITCHEN)
    n = 30
    src = get_pose_source("kiss-icp")
    poses = run_source(src, seq, n)
    acc = trajectory_accuracy((seq.timestamps[:n], poses), (seq.timestamps[:n], seq.poses[:n]))
    assert acc["ate_rmse_m"] < 0.02, acc


# -- pycolmap ---------------------------------------------------------------------------------------------------------
class FrameSubset:
    """The first frames of a sequence, every ``step``-th (an in-memory sequence: no colour files)."""

    def __init__(self, seq, n: int, step: int = 1):
        self.seq, self.ids = seq, list(range(0, n * step, step))
        self.camera, self.name = seq.camera, f"{seq.name}[:{n}:{step}]"
        self.timestamps = seq.timestamps[self.ids]
        self.poses = [seq.poses[i] for i in self.ids]
        self.color_paths = []

    def __len__(self):
        return len(self.ids)

    def __getitem__(self, i):
        return self.seq[self.ids[i]]

    def frame(self, i):
        return self.seq.frame(self.ids[i])


@pytest.fixture(scope="module")
def colmap_run(tmp_path_factory):
    pytest.importorskip("pycolmap")
    if not STUDYROOM.is_dir():
        pytest.skip("needs ../shared/data/sun3d_mit76_studyroom_f0935")
    seq = FrameSubset(open_sequence(STUDYROOM), 10, step=5)
    work = tmp_path_factory.mktemp("colmap")
    src = get_pose_source("colmap", sequence=seq, work_dir=work)
    src.prepare()
    return seq, src, work


def test_colmap_recovers_metric_trajectory(colmap_run):
    seq, src, _ = colmap_run
    assert src.registered == len(seq)
    poses = [src.track(i, seq.timestamps[i], None, None, seq.camera, gt_pose=seq.poses[0] if i == 0 else None)
             for i in range(len(seq))]
    acc = trajectory_accuracy((seq.timestamps, poses), (seq.timestamps, seq.poses))
    assert acc["ate_rmse_m"] < 0.03, acc
    scale = trajectory_accuracy((seq.timestamps, poses), (seq.timestamps, seq.poses), with_scale=True)["scale"]
    assert scale == pytest.approx(1.0, abs=0.1)
    np.testing.assert_allclose(poses[0], seq.poses[0], atol=1e-9)


def test_colmap_model_import(colmap_run):
    seq, src, work = colmap_run
    imported = get_pose_source(str(work / "sparse"), sequence=seq)
    imported.prepare()
    assert imported.metric_scale == pytest.approx(src.metric_scale, rel=1e-6)
    a, b = src.poses(), imported.poses()
    assert a.keys() == b.keys()
    for i in a:
        Ta, Tb = invert_pose(a[0]) @ a[i], invert_pose(b[0]) @ b[i]
        np.testing.assert_allclose(Ta, Tb, atol=1e-6)
    with pytest.raises(TrackingLost, match="frame 99: COLMAP did not register"):
        imported.track(99, 0.0, None, None, seq.camera)


def test_colmap_failure_is_clear():
    pytest.importorskip("pycolmap")
    seq = FrameSubset(open_sequence("synthetic", n_frames=240, width=160, height=120), 3)
    flat = np.full((120, 160, 3), 128, np.uint8)

    class Blank(FrameSubset):
        def __getitem__(self, i):
            item = super().__getitem__(i)
            item.rgbd = o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3c.Tensor(flat)), item.rgbd.depth)
            return item

    blank = Blank(seq.seq, 3)
    with pytest.raises(RuntimeError, match="incremental mapping failed"):
        get_pose_source("colmap").prepare(blank)


def test_one_tum_reader_one_rule(tmp_path):
    """Trajectory files and datasets' ground truth are read by the same reader: timestamps must increase."""
    from eligsir_o3d.datasets.base import DatasetError

    p = tmp_path / "unsorted.txt"
    p.write_text("0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"unsorted\.txt:2: timestamp 0\.100000 is not after"):
        read_tum_trajectory(p)
    p.write_text("# only a header\n")
    with pytest.raises(ValueError, match="no poses"):
        read_tum_trajectory(p)


def test_colmap_import_takes_the_largest_of_several_models(tmp_path):
    """Incremental mapping can leave sparse/0 and sparse/1; the import must take the bigger one, as the SfM run does
    (taking sparse/0 made the model-import test fail whenever mapping split the images under load)."""
    from eligsir_o3d.pose.colmap import find_model_dir

    for k, n in (("0", 10), ("1", 1000)):
        d = tmp_path / "sparse" / k
        d.mkdir(parents=True)
        for name in ("cameras", "points3D"):
            (d / f"{name}.bin").write_bytes(b"x")
        (d / "images.bin").write_bytes(b"x" * n)
    assert find_model_dir(tmp_path) == tmp_path / "sparse" / "1"
    assert find_model_dir(tmp_path / "sparse" / "0") == tmp_path / "sparse" / "0"
    assert find_model_dir(tmp_path / "nothing") is None
