"""Maps for the web: map.spz read back by an independent reader (PlayCanvas' splat-transform, run with node)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from eligsir_o3d import Config
from eligsir_o3d.export.viewers import write_for_viewers
from eligsir_o3d.export.web import parse_formats, rdf_to_rub, splat_cloud, spz_order, write_web
from eligsir_o3d.io.ply import load_ply
from eligsir_o3d.run.pipeline import RunOptions, run_mapping

ROOT = Path(__file__).resolve().parents[2]
SEVEN = ROOT / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
pytestmark = pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data is not available")


def _splat_transform() -> list[str] | None:  # node + PlayCanvas splat-transform, where installed
    exe = Path(os.environ.get("ELIGSIR_SPLAT_TRANSFORM", ROOT / ".npm" / "node_modules" / ".bin" / "splat-transform"))
    if not exe.exists() or shutil.which("node") is None:
        return None
    return ["node", str(exe)]


def _run(tmp_path, sh_degree: int, frames: int = 16) -> Path:
    cfg = Config(renderer="cpu", sh_degree=sh_degree)
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 3, 30
    out = tmp_path / f"run_sh{sh_degree}"
    run_mapping(str(SEVEN), out, cfg, RunOptions(max_frames=frames, eval_every=0, progress=False, plots=False,
                                                  pictures=False, formats="ply,spz,splat"))
    return out


@pytest.fixture(scope="module")
def run_sh0(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("web"), 0)


def read_splats(map_ply: Path):
    """A 3DGS PLY as Open3D's reader makes it (a Gaussian-splat point cloud)."""
    import open3d as o3d

    return o3d.t.io.read_point_cloud(str(map_ply))


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _spz_streams(path: Path) -> tuple[int, dict]:
    """(Gaussian count, {stream: compressed bytes}) of an SPZ v4 file, from its header and table of contents."""
    import struct

    data = path.read_bytes()
    magic, version, n, _sh, _bits, _flags, count, toc = struct.unpack_from("<IIIBBBBI", data, 0)
    assert (magic, version) == (0x5053474E, 4)
    names = ("positions", "alphas", "colors", "scales", "rotations", "sh")
    sizes = {names[i]: struct.unpack_from("<QQ", data, toc + 16 * i)[0] for i in range(count)}
    assert 32 + 16 * count + sum(sizes.values()) == len(data)
    return n, sizes


def test_map_writes_spz_and_splat_beside_the_ply(run_sh0, tmp_path):
    import open3d as o3d

    for name in ("map.ply", "map.spz", "map.splat"):
        assert (run_sh0 / name).stat().st_size > 0
    ply, spz = (run_sh0 / "map.ply").stat().st_size, (run_sh0 / "map.spz").stat().st_size
    n, sizes = _spz_streams(run_sh0 / "map.spz")
    assert n > 500 and ply == pytest.approx(68 * n, abs=2000)  # SH degree 0: 17 floats a Gaussian (normals too)
    # the same Gaussians written in the PLY's order: written in opacity order instead, the 8-bit opacity stream
    # becomes runs (over 2x smaller), and no other stream grows by more than a few bytes
    o3d.t.io.write_point_cloud(str(tmp_path / "plain.spz"), rdf_to_rub(read_splats(run_sh0 / "map.ply")))
    _, plain = _spz_streams(tmp_path / "plain.spz")
    assert sizes["alphas"] * 2 < plain["alphas"], (sizes, plain)
    assert all(sizes[k] <= plain[k] * 1.02 + 16 for k in sizes if k != "alphas"), (sizes, plain)
    assert ply / spz > 4.2, (ply, spz, n, sizes)  # 4.37x here; 4.3x on the 200-frame kitchen map (docs/phone.md)


def test_spz_read_back_by_splat_transform_matches_the_map(run_sh0, tmp_path):
    """splat-transform decodes SPZ without any axis conversion, so its output must equal our map turned to RUB
    (the SPZ spec's axes) within SPZ's quantisation: the map as web players should draw it, its low-pass baked
    in (what `eligsir export --for-viewers` writes)."""
    cmd = _splat_transform()
    if cmd is None:
        pytest.skip("splat-transform not installed (tools/setup.sh --test installs it into .npm/)")
    back = tmp_path / "back.ply"
    ref = tmp_path / "for_viewers.ply"
    write_for_viewers(run_sh0 / "map.ply", ref)
    subprocess.run([*cmd, "-w", str(run_sh0 / "map.spz"), str(back)], check=True, capture_output=True, timeout=120)
    from plyfile import PlyData

    b = PlyData.read(str(back), mmap=False)["vertex"]
    m = PlyData.read(str(ref), mmap=False)["vertex"]  # the map as written: RDF, log scales, logits
    m = m.data[spz_order(read_splats(ref))]  # the SPZ holds the Gaussians in opacity order
    flip = np.array([1.0, -1.0, -1.0])
    a = {"positions": np.stack([m["x"], m["y"], m["z"]], 1) * flip,
         "rot": np.stack([m[f"rot_{i}"] for i in range(4)], 1) * np.array([1.0, 1.0, -1.0, -1.0]),
         "scale": np.stack([m[f"scale_{i}"] for i in range(3)], 1), "opacity": np.asarray(m["opacity"])[:, None],
         "f_dc": np.stack([m[f"f_dc_{i}"] for i in range(3)], 1)}
    assert len(b["x"]) == len(a["positions"]) > 100
    pos = np.stack([b["x"], b["y"], b["z"]], 1)
    np.testing.assert_allclose(pos, a["positions"], atol=2.0 ** -12 + 1e-6)  # 12 fractional bits
    np.testing.assert_allclose(np.stack([b[f"scale_{i}"] for i in range(3)], 1), a["scale"], atol=1 / 32 + 1e-4)
    np.testing.assert_allclose(_sigmoid(b["opacity"]), _sigmoid(a["opacity"][:, 0]), atol=1 / 255 + 1e-4)
    np.testing.assert_allclose(np.stack([b[f"f_dc_{i}"] for i in range(3)], 1), a["f_dc"], atol=0.02)
    q_ref = a["rot"] / np.linalg.norm(a["rot"], axis=1, keepdims=True)
    q = np.stack([b[f"rot_{i}"] for i in range(4)], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert np.abs(np.sum(q * q_ref, axis=1)).min() > 0.995  # same rotation (q and -q alike), ~10-bit components
    # the axis turn is there: y and z of the SPZ are the map's, negated
    raw = read_splats(ref)
    np.testing.assert_allclose(pos[:, 1:], -raw.point.positions.numpy()[spz_order(raw)][:, 1:], atol=2.0 ** -12 + 1e-6)


def test_spz_is_six_times_smaller_at_sh_degree_3(tmp_path):
    out = _run(tmp_path, 3, frames=8)
    ratio = (out / "map.ply").stat().st_size / (out / "map.spz").stat().st_size
    assert ratio >= 6.0, ratio


def test_rub_turn_flips_sh_signs_and_is_its_own_inverse(run_sh0):
    pcd = read_splats(run_sh0 / "map.ply")
    twice = rdf_to_rub(rdf_to_rub(pcd))
    for k in ("positions", "rot", "scale", "opacity", "f_dc"):
        np.testing.assert_array_equal(twice.point[k].numpy(), pcd.point[k].numpy().astype(np.float32))


def test_formats_and_bad_paths():
    assert parse_formats("spz, ply,splat") == ["ply", "spz", "splat"]
    with pytest.raises(ValueError, match="unknown map format"):
        parse_formats("ply,gltf")
    from eligsir_o3d.core.gaussians import GaussianMap

    with pytest.raises(ValueError, match="nothing to write"):
        write_web(GaussianMap(0))


def test_spz_refuses_positions_its_fixed_point_cannot_hold(run_sh0, tmp_path):
    far = load_ply(run_sh0 / "map.ply")
    far.params["means"].data += 3000.0  # 3 km off: beyond 2^23 / 2^12 m
    with pytest.raises(ValueError, match=r"far\.spz: a Gaussian lies 30\d\d m from the origin; SPZ positions reach 2048 m"):
        write_web(far, spz=tmp_path / "far.spz")
    assert not (tmp_path / "far.spz").exists()


@pytest.mark.parametrize("sh_degree", [0, 2])
def test_the_map_in_memory_is_what_open3d_reads_from_its_ply(tmp_path, sh_degree):
    """splat_cloud is, field for field and bit for bit, Open3D's reading of the map's PLY; so SPZ and .splat
    written from memory are the bytes the PLY would give, with no PLY written."""
    import open3d as o3d
    import torch

    from eligsir_o3d.core.gaussians import GaussianMap
    from eligsir_o3d.io.ply import save_ply

    g = torch.Generator().manual_seed(sh_degree)
    gm = GaussianMap(sh_degree)
    n = 5000
    gm.add(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g) * 0.1, 0.5)
    gm.params["scales"].data = torch.empty(n, 3).uniform_(-12.0, 2.0, generator=g)
    gm.params["quats"].data = torch.randn(n, 4, generator=g)
    gm.params["opacities"].data = torch.randn(n, generator=g) * 4
    gm.params["shN"].data = torch.randn(gm.params["shN"].shape, generator=g)
    ref = read_splats(save_ply(gm, tmp_path / "m.ply"))
    mine = splat_cloud(gm)
    for key in ("positions", "f_dc", "f_rest", "opacity", "scale", "rot"):
        assert (key in mine.point) == (key in ref.point), key
        if key in ref.point:
            np.testing.assert_array_equal(mine.point[key].numpy(), ref.point[key].numpy(), err_msg=key)
    write_web(gm, spz=tmp_path / "a.spz", splat=tmp_path / "a.splat")
    plain = o3d.t.geometry.PointCloud()
    for key in ("positions", "f_dc", "opacity", "scale", "rot", "f_rest"):
        if key in ref.point:
            plain.point[key] = ref.point[key]
    o3d.t.io.write_point_cloud(str(tmp_path / "b.splat"), plain)
    rub = rdf_to_rub(ref)
    order = spz_order(rub)
    reordered = o3d.t.geometry.PointCloud()
    for key in ("positions", "f_dc", "opacity", "scale", "rot", "f_rest"):
        if key in rub.point:
            reordered.point[key] = o3d.core.Tensor(np.ascontiguousarray(rub.point[key].numpy()[order]))
    o3d.t.io.write_point_cloud(str(tmp_path / "b.spz"), reordered)
    assert (tmp_path / "a.splat").read_bytes() == (tmp_path / "b.splat").read_bytes()
    assert (tmp_path / "a.spz").read_bytes() == (tmp_path / "b.spz").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.splat", "a.spz", "b.splat", "b.spz", "m.ply"]


def test_heldout_picture_of_real_frames_is_at_most_300_kB():
    import io

    import torch
    from PIL import Image

    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.visual.pictures import MAX_PICTURE_BYTES, comparison_picture, small_png

    seq = open_sequence(SEVEN)
    f, g = seq.frame(10), seq.frame(14)  # a neighbouring frame stands in for a render: real texture, real errors
    pic = comparison_picture(f.color, f.depth, g.color, g.depth, torch.ones_like(g.depth), "held-out frame 10")
    data = small_png(pic)
    assert len(data) <= MAX_PICTURE_BYTES == 300_000
    back = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    assert back.shape == pic.shape  # still full size: legible
    mse = np.mean((back.astype(float) - pic.astype(float)) ** 2)
    assert 10 * np.log10(255.0 ** 2 / mse) > 30.0  # 256 colours, no dithering: text and colour maps intact


def _draw_spz(spz: Path, tmp_path: Path, tag: str) -> np.ndarray:
    """Screenshot [H, W, 3] of ``spz`` drawn by the SuperSplat viewer (splat-transform's .html output) in headless
    Chromium (software WebGL)."""
    import functools
    import http.server
    import sys
    import threading
    import time

    from helpers.headless_browser import HeadlessChromium

    html = tmp_path / f"{tag}.html"
    subprocess.run([*_splat_transform(), "-w", str(spz), str(html)], check=True, capture_output=True, timeout=300)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with HeadlessChromium(640, 480, timeout_s=60) as browser:
            browser.open(f"http://127.0.0.1:{server.server_port}/{html.name}?webgl&noanim&noui")
            time.sleep(12)  # decode, upload, sort, first frames on a software GL
            return browser.screenshot()
    finally:
        server.shutdown()


def test_spz_is_drawn_in_headless_chromium(run_sh0, tmp_path):
    from helpers.headless_browser import find_chromium

    if _splat_transform() is None or find_chromium() is None:
        pytest.skip("needs splat-transform (.npm/) and chromium (tools/setup.sh --test)")
    pcd = read_splats(run_sh0 / "map.ply")
    clear = rdf_to_rub(pcd)  # the same map with every Gaussian transparent: the viewer must draw (almost) nothing
    clear.point["opacity"] = clear.point["opacity"] * 0.0 - 12.0
    import open3d as o3d

    o3d.t.io.write_point_cloud(str(tmp_path / "clear.spz"), clear)
    shown = _draw_spz(run_sh0 / "map.spz", tmp_path, "map")
    empty = _draw_spz(tmp_path / "clear.spz", tmp_path, "clear")
    lit = lambda img: float((img.max(axis=2) > 40).mean())  # noqa: E731
    assert lit(shown) > 0.02 and lit(empty) < 0.005, (lit(shown), lit(empty))
