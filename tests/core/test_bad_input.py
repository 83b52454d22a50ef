"""Bad input, table-driven: each case feeds one bad input to a public entry point (Reconstructor.integrate,
render, load_ply, load_state_dict of a checkpoint, open_sequence / seq[i] -> integrate, Config.load, a trajectory
file's pose source) and asserts a clear error naming the file, frame and field, and that the map already built
(Gaussian parameters, counters, retained views) is unchanged. Then the CLI: a bad frame in a run is reported and
skipped, or stops the run with a one-line error (no traceback); a bad config, trajectory, checkpoint or PLY file
ends the command with one line naming the file and the problem (exit 2)."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

import eligsir_o3d as eo3d
from eligsir_o3d.core.camera import pose_to_tum
from eligsir_o3d.io.checkpoint import CheckpointError, read_checkpoint
from eligsir_o3d.config import ConfigError
from eligsir_o3d.datasets import DatasetError, open_sequence
from eligsir_o3d.core.frame import FrameError
from eligsir_o3d.io.ply import PlyError
from eligsir_o3d.pose import TrajectoryError, get_pose_source, write_tum_trajectory

W, H, N = 40, 30, 6


def _write_folder(root: Path, n: int = N) -> None:
    """The synthetic room as a plain folder sequence (color/, depth/ 16-bit PNG, intrinsics.json, poses.txt)."""
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    seq = open_sequence("synthetic", n_frames=n, width=W, height=H, depth_dtype="uint16")
    lines = []
    for i in range(n):
        item = seq[i]
        o3d.t.io.write_image(str(root / "color" / f"{i:06d}.png"), item.rgbd.color)
        o3d.t.io.write_image(str(root / "depth" / f"{i:06d}.png"), item.rgbd.depth)
        t, q = pose_to_tum(item.T_world_cam)
        lines.append(f"{item.timestamp:.6f} " + " ".join(f"{x:.9f}" for x in (*t, *q)))
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    c = seq.camera
    (root / "intrinsics.json").write_text(json.dumps({"width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy,
                                                      "cx": c.cx, "cy": c.cy, "depth_scale": 1000.0}))


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("seq") / "room"
    _write_folder(root)
    return root


@pytest.fixture(scope="module")
def seq(folder):
    return open_sequence(folder)


@pytest.fixture
def built(seq):
    """A Reconstructor that has mapped the first two frames of the folder sequence (fresh for every case: a case
    that wrongly succeeds must not leak into the next)."""
    cfg = eo3d.Config()
    cfg.depth_scale = seq.depth_scale
    rec = eo3d.Reconstructor(seq.intrinsic, "cpu", cfg)
    for i in range(2):
        item = seq[i]
        rec.integrate(item.rgbd, item.T_world_cam, timestamp=item.timestamp, updates=2)
    return rec, seq


def _snapshot(rec):
    return ({k: v.detach().clone() for k, v in rec.gmap.params.items()},
            {k: v for k, v in vars(rec.stats).items() if not k.endswith("_s")},
            [(f.index, f.timestamp) for f in rec.views.views], rec.config.to_dict())


def _rgbd(color, depth):
    return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(color))),
                                    o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth))))


def _good(seq, i=2):
    item = seq[i]
    return item.rgbd.color.as_tensor().numpy().copy(), item.rgbd.depth.as_tensor().numpy()[..., 0].copy(), \
        item.T_world_cam, item.timestamp


def _integrate(color=None, depth=None, pose=None, timestamp=None, i=2):
    def run(rec, seq, tmp):
        c, d, T, ts = _good(seq, i)
        rec.integrate(_rgbd(c if color is None else color(c), d if depth is None else depth(d)),
                      T if pose is None else pose(T), timestamp=ts if timestamp is None else timestamp)
    return run


def _from_folder(edit, index=2, after_open=False):
    """Copy the folder sequence, damage it with ``edit(root)`` (before or after opening it), open it and
    integrate frame ``index``."""
    def run(rec, seq, tmp):
        root = tmp / "damaged"
        shutil.copytree(seq.path, root)
        if not after_open:
            edit(root)
        s = open_sequence(root)
        if after_open:
            edit(root)
        item = s[index]
        rec.integrate(item.rgbd, item.T_world_cam, timestamp=item.timestamp)
    return run


def _nonrigid(T):
    T = T.copy()
    T[:3, :3] *= 1.5
    return T


def _nan_pose(T):
    T = T.copy()
    T[0, 3] = np.nan
    return T


def _ply_edit(drop=(), add=()):
    """The map's PLY with vertex properties ``drop`` removed and ``add`` (zeros) appended, loaded back."""
    def run(rec, seq, tmp):
        from plyfile import PlyData, PlyElement

        rec.save_ply(tmp / "full.ply")
        v = PlyData.read(str(tmp / "full.ply"))["vertex"].data
        keep = [n for n in v.dtype.names if n not in drop]
        arr = np.zeros(len(v), dtype=[(n, "f4") for n in [*keep, *add]])
        for n in keep:
            arr[n] = v[n]
        PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp / "bad.ply"))
        rec.load_ply(tmp / "bad.ply")
    return run


def _ply_text(text):
    def run(rec, seq, tmp):
        (tmp / "bad.ply").write_bytes(text)
        rec.load_ply(tmp / "bad.ply")
    return run


def _ply_nan(field="x", value=np.nan):
    def run(rec, seq, tmp):
        from plyfile import PlyData

        rec.save_ply(tmp / "full.ply")
        ply = PlyData.read(str(tmp / "full.ply"), mmap=False)
        ply["vertex"].data[field][0] = value
        ply.write(str(tmp / "nan.ply"))
        rec.load_ply(tmp / "nan.ply")
    return run


def _ply_bytes(edit):
    """The map's PLY with its bytes changed by ``edit(data)``, loaded back into the map."""
    def run(rec, seq, tmp):
        rec.save_ply(tmp / "full.ply")
        (tmp / "bad.ply").write_bytes(edit((tmp / "full.ply").read_bytes()))
        rec.load_ply(tmp / "bad.ply")
    return run


def _vertex_count(delta):
    return lambda data: re.sub(rb"element vertex (\d+)", lambda m: b"element vertex %d" % (int(m[1]) + delta),
                               data, count=1)


def _config_file(data):
    def run(rec, seq, tmp):
        (tmp / "cfg.json").write_text(json.dumps(data))
        eo3d.Config.load(tmp / "cfg.json")
    return run


def _short_trajectory(n_poses):
    """A TUM trajectory of the first ``n_poses`` frames, as the pose source of all the sequence's frames."""
    def run(rec, seq, tmp):
        path = write_tum_trajectory(tmp / "short.txt", seq.timestamps[:n_poses], seq.poses[:n_poses])
        src = get_pose_source(str(path), sequence=seq)
        src.prepare()
        src.check_frames(seq, range(len(seq)))
    return run


def _checkpoint_version(version):
    """The map's own checkpoint with its format version changed, loaded back into the map."""
    def run(rec, seq, tmp):
        rec.save(tmp / "ck.pt")
        raw = torch.load(tmp / "ck.pt", weights_only=True)
        if version is None:
            raw.pop("version")
        else:
            raw["version"] = version
        torch.save(raw, tmp / "ck.pt")
        rec.load_state_dict(read_checkpoint(tmp / "ck.pt"))
    return run


def _write(rel, data):
    return lambda root: (root / rel).write_bytes(data)


def _replace_line(rel, lineno, fn):
    def edit(root):
        lines = (root / rel).read_text().splitlines()
        lines[lineno] = fn(lines[lineno])
        (root / rel).write_text("\n".join(lines) + "\n")
    return edit


def _swap_timestamps(line):
    fields = line.split()
    fields[0] = "0.010000"  # frame 2 at 10 ms, after frame 1 at 33 ms
    return " ".join(fields)


def _resize_intrinsics(root):
    data = json.loads((root / "intrinsics.json").read_text())
    data.update(width=64, height=48)
    (root / "intrinsics.json").write_text(json.dumps(data))


def _empty(root):
    for sub in ("color", "depth"):
        shutil.rmtree(root / sub)
        (root / sub).mkdir()
    (root / "poses.txt").unlink()


def _eight_bit_depth(root):
    d = o3d.t.io.read_image(str(root / "depth" / "000002.png")).as_tensor().numpy()
    o3d.t.io.write_image(str(root / "depth" / "000002.png"),
                         o3d.t.geometry.Image(o3d.core.Tensor((d // 100).astype(np.uint8))))


CASES = [
    # --- Reconstructor.integrate: images, dtypes, depth, pose, intrinsics, timestamps ---
    ("colour and depth sizes differ", _integrate(depth=lambda d: d[:, :-2]), FrameError,
     r"frame 2: colour 40x30 and depth 38x30 sizes differ"),
    ("colour dtype int32", _integrate(color=lambda c: c.astype(np.int32)), FrameError,
     r"frame 2: unsupported colour dtype int32"),
    ("depth dtype bool", _integrate(depth=lambda d: d > 0), FrameError, r"frame 2: unsupported depth dtype bool"),
    ("float colour out of [0, 1]", _integrate(color=lambda c: c.astype(np.float32)), FrameError,
     r"frame 2: float colour must be in \[0, 1\]"),
    ("NaN colour", _integrate(color=lambda c: np.full(c.shape, np.nan, np.float32)), FrameError,
     r"frame 2: colour contains NaN"),
    ("all-zero depth", _integrate(depth=lambda d: np.zeros_like(d)), FrameError,
     r"frame 2: depth has no valid measurement"),
    ("all-NaN depth", _integrate(depth=lambda d: np.full(d.shape, np.nan, np.float32)), FrameError,
     r"frame 2: depth is all NaN"),
    ("NaN pose", _integrate(pose=_nan_pose), FrameError, r"frame 2: pose: contains NaN"),
    ("non-rigid pose", _integrate(pose=_nonrigid), FrameError, r"frame 2: pose: .*non-rigid"),
    ("pose not 4x4", _integrate(pose=lambda T: T[:3]), FrameError, r"frame 2: pose: expected a 4x4 matrix"),
    ("intrinsics do not match the image", _integrate(color=lambda c: np.zeros((24, 32, 3), np.uint8),
                                                     depth=lambda d: np.full((24, 32), 1000, np.uint16)),
     FrameError, r"frame 2: intrinsics are for 40x30 but the image is 32x24"),
    ("timestamp goes backwards", _integrate(timestamp=0.01), FrameError, r"frame 2: timestamp 0\.01.* not after"),
    ("not an RGBD image", lambda rec, seq, tmp: rec.integrate(np.zeros((H, W, 3)), np.eye(4)), FrameError,
     r"frame 2: expected an Open3D RGBDImage"),
    ("no pose and no pose source", lambda rec, seq, tmp: rec.integrate(seq[2].rgbd, None), FrameError,
     r"frame 2: no pose given and no pose source"),
    ("render at a NaN pose", lambda rec, seq, tmp: rec.render(np.full((4, 4), np.nan)), ValueError,
     r"render pose: contains NaN"),
    # --- recorded sequences: files, timestamps, intrinsics, emptiness ---
    ("colour file deleted after opening", _from_folder(lambda r: (r / "color" / "000002.png").unlink(),
                                                       after_open=True), DatasetError,
     r"frame 2: colour file .*color/000002\.png does not exist"),
    ("missing depth file", _from_folder(lambda r: (r / "depth" / "000002.png").unlink()), DatasetError,
     r"6 colour images in .*color but 5 depth PNGs in .*depth.*no depth PNGs in .* named like 000002\.png"),
    ("corrupt colour file", _from_folder(_write("color/000002.png", b"\x89PNG not really")), DatasetError,
     r"frame 2: colour file .*color/000002\.png is corrupt or not an image"),
    ("corrupt depth file", _from_folder(_write("depth/000002.png", b"")), DatasetError,
     r"frame 2: depth file .*depth/000002\.png is corrupt or not an image"),
    ("8-bit depth file", _from_folder(_eight_bit_depth), DatasetError,
     r"frame 2: depth file .*depth/000002\.png must be a single-channel 16-bit image"),
    ("timestamps go backwards", _from_folder(_replace_line("poses.txt", 2, _swap_timestamps)), DatasetError,
     r"poses\.txt:3: timestamp 0\.010000 is not after the previous line's 0\.033333"),
    ("NaN in a pose file", _from_folder(_replace_line("poses.txt", 1, lambda s: s.rsplit(" ", 1)[0] + " nan")),
     DatasetError, r"poses\.txt:2: non-finite value"),
    ("intrinsics do not match the images", _from_folder(_resize_intrinsics), DatasetError,
     r"frame 2: colour file .*000002\.png is 40x30 but the intrinsics are for 64x48"),
    ("empty sequence", _from_folder(_empty), DatasetError, r"color: no \.png or \.jpg images \(empty sequence\)"),
    # --- Gaussian PLY files ---
    ("PLY missing attributes", _ply_edit(drop={"opacity", "rot_0"}), PlyError,
     r"bad\.ply: not a 3DGS Gaussian PLY, missing vertex properties \['opacity', 'rot_0'\]"),
    ("PLY with a partial SH set", _ply_edit(drop={f"f_rest_{i}" for i in range(45)},
                                            add=[f"f_rest_{i}" for i in range(5)]), PlyError,
     r"bad\.ply: 5 f_rest_\* properties do not match any SH degree"),
    ("PLY that is not a PLY", _ply_text(b"solid cube\nendsolid\n"), PlyError, r"bad\.ply: not a readable PLY"),
    ("PLY with NaN", _ply_nan(), PlyError, r"nan\.ply: property group 'means' contains NaN"),
    ("PLY with an infinite opacity", _ply_nan("opacity", np.inf), PlyError,
     r"nan\.ply: property group 'opacities' contains NaN or Inf"),
    ("PLY that does not exist", lambda rec, seq, tmp: rec.load_ply(tmp / "none.ply"), PlyError,
     r"none\.ply: no such file"),
    ("PLY truncated", _ply_bytes(lambda data: data[:-100]), PlyError,
     r"bad\.ply: wrong vertex count: the header declares \d+ \(\d+ bytes\) but the file holds \d+ bytes of data, "
     r"\d+ whole vertex rows \(truncated\?\)"),
    ("PLY header declares more vertices", _ply_bytes(_vertex_count(+3)), PlyError,
     r"bad\.ply: wrong vertex count: the header declares \d+ .*\(truncated\?\)"),
    ("PLY header declares fewer vertices", _ply_bytes(_vertex_count(-3)), PlyError,
     r"bad\.ply: wrong vertex count: the header declares \d+ \(\d+ bytes\) but the file holds \d+ bytes of data, "
     r"\d+ whole vertex rows$"),
    # --- config files ---
    ("config file with a string for an integer", _config_file({"clock": {"updates_per_frame": "ten"}}), ConfigError,
     r"cfg\.json: clock\.updates_per_frame takes an integer, got str 'ten'"),
    ("config file with a bool for an integer", _config_file({"views": {"active_size": True}}), ConfigError,
     r"cfg\.json: views\.active_size takes an integer, got bool True"),
    ("config file with a string for a list", _config_file({"ablate": "views"}), ConfigError,
     r"cfg\.json: ablate takes a list, got str 'views'"),
    ("config file with a number for a string", _config_file({"clock": {"mode": 3}}), ConfigError,
     r"cfg\.json: clock\.mode takes a string, got int 3"),
    # --- trajectory files ---
    ("trajectory file with fewer poses than frames", _short_trajectory(3), TrajectoryError,
     r"short\.txt: 3 poses for 6 frames: the trajectory covers t=0\.000-0\.067 s but 3 of the frames lie outside "
     r"it \(the first: frame 3 at t=0\.100 s\)"),
    # --- checkpoints ---
    ("checkpoint from a newer format version", _checkpoint_version(2), CheckpointError,
     r"ck\.pt: checkpoint version 2 is newer than this eligsir_o3d reads \(1\); upgrade the package"),
    ("checkpoint from an older format version", _checkpoint_version(0), CheckpointError,
     r"ck\.pt: checkpoint version 0 is older than this eligsir_o3d reads \(1\); map the sequence again"),
    ("checkpoint without a format version", _checkpoint_version(None), CheckpointError,
     r"ck\.pt: checkpoint version 0 is older than this eligsir_o3d reads"),
]


@pytest.mark.parametrize("name, action, error, message",
                         [c if hasattr(c, "marks") else pytest.param(*c, id=c[0]) for c in CASES])
def test_bad_input_raises_clearly_and_leaves_the_map(built, tmp_path, name, action, error, message):
    rec, seq = built
    before = _snapshot(rec)
    with pytest.raises(error, match=message):
        action(rec, seq, tmp_path)
    params, counters, views, config = _snapshot(rec)
    assert counters == before[1] and views == before[2] and config == before[3]
    for k, v in before[0].items():
        assert torch.equal(params[k], v), k


def test_cli_skips_or_stops_on_a_bad_frame(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    root = tmp_path / "room"
    _write_folder(root)
    (root / "color" / "000003.png").write_bytes(b"garbage")
    cfg = eo3d.Config()
    cfg.clock.updates_per_frame, cfg.clock.drain_updates = 1, 0
    cfg.save(tmp_path / "cfg.json")
    common = [str(root), "--holdout-every", "5", "--eval-every", "0", "--config", str(tmp_path / "cfg.json"), "-q"]
    runner = CliRunner()
    r = runner.invoke(app, ["map", *common, "--out", str(tmp_path / "skip")])
    assert r.exit_code == 0, r.output
    skipped = json.loads((tmp_path / "skip" / "metrics.json").read_text())["skipped_frames"]
    assert len(skipped) == 1 and "frame 3" in skipped[0] and "000003.png is corrupt" in skipped[0], skipped
    r = runner.invoke(app, ["map", *common, "--out", str(tmp_path / "stop"), "--on-bad-frame", "stop"])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert "error: frame 3: colour file" in r.output and "000003.png is corrupt" in r.output, r.output


def _cli_bad_file(kind, folder, tmp):
    """(eligsir arguments, expected one-line error) for a malformed input file of ``kind``."""
    seq = open_sequence(folder)
    run = [str(folder), "--holdout-every", "3", "--eval-every", "0", "--updates-per-frame", "1", "--no-pictures",
           "-q", "--out", str(tmp / "out")]
    if kind == "config":
        (tmp / "cfg.json").write_text(json.dumps({"views": {"active_size": "many"}}))
        return ["map", *run, "--config", str(tmp / "cfg.json")], \
            r"^error: .*cfg\.json: views\.active_size takes an integer, got str 'many'$"
    if kind == "trajectory":
        write_tum_trajectory(tmp / "short.txt", seq.timestamps[:2], seq.poses[:2])
        return ["map", *run, "--pose", str(tmp / "short.txt")], \
            r"^error: .*short\.txt: 2 poses for 4 frames: .* lie outside it \(the first: frame 2 at t=0\.067 s\)"
    if kind in ("newer checkpoint", "older checkpoint"):
        rec = eo3d.Reconstructor(seq.intrinsic, "cpu", eo3d.Config())
        rec.save(tmp / "out" / "checkpoint.pt")
        raw = torch.load(tmp / "out" / "checkpoint.pt", weights_only=True)
        raw["version"] = 5 if kind == "newer checkpoint" else 0
        torch.save(raw, tmp / "out" / "checkpoint.pt")
        return ["map", *run, "--resume"], \
            rf"^error: .*checkpoint\.pt: checkpoint version {raw['version']} is (newer|older) than this eligsir_o3d"
    if kind == "PLY":
        rec = eo3d.Reconstructor(seq.intrinsic, "cpu", eo3d.Config())
        item = seq[0]
        rec.integrate(item.rgbd, item.T_world_cam, timestamp=item.timestamp, updates=0)
        rec.save_ply(tmp / "map.ply")
        data = (tmp / "map.ply").read_bytes()
        (tmp / "map.ply").write_bytes(data[: len(data) - 10])
        return ["export", str(tmp / "map.ply"), "--point-cloud", str(tmp / "cloud.ply")], \
            r"^error: .*map\.ply: wrong vertex count: the header declares \d+ .*\(truncated\?\)$"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["config", "trajectory", "newer checkpoint", "older checkpoint", "PLY"])
def test_cli_names_a_malformed_input_file_in_one_line(folder, tmp_path, kind):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    args, expected = _cli_bad_file(kind, folder, tmp_path)
    r = CliRunner().invoke(app, args)
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert r.exit_code == 2 and "Traceback" not in r.output and len(lines) == 1, r.output
    assert re.search(expected, lines[0]), lines[0]
    assert not (tmp_path / "out" / "metrics.json").exists()
