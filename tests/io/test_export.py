"""Geometry export: point cloud and mesh of a map of the synthetic room against its known geometry, the 3DGS PLY
read back by plyfile and by Open3D, and ``export_from_ply`` (what ``eligsir export`` runs)."""

import json
from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest
import torch

import eligsir_o3d as eo3d
from eligsir_o3d.core.camera import pose_to_tum
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.export import export_from_ply, extract_point_cloud, extract_triangle_mesh
from eligsir_o3d.export.geometry import orient_towards
from eligsir_o3d.export.views import sphere_poses
from eligsir_o3d.core.gaussians import GaussianMap, sh0_to_rgb
from eligsir_o3d.io.ply import PlyError, load_ply, save_ply

N_FRAMES, W, H = 12, 80, 60


@pytest.fixture(scope="module")
def scene():
    """The synthetic room, its frames, and the ground-truth surface they observe (back-projected exact depth,
    with colours and camera-facing normals)."""
    seq = open_sequence("synthetic", n_frames=N_FRAMES, width=W, height=H)
    frames = [seq.frame(i) for i in range(len(seq))]
    pts, cols = [], []
    for f in frames:
        p, idx = f.camera.backproject(f.depth)
        T = f.T_world_cam
        pts.append(p.numpy() @ T[:3, :3].T + T[:3, 3])
        cols.append(f.color.reshape(-1, 3)[idx].numpy())
    gt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts)))
    gt.colors = o3d.utility.Vector3dVector(np.concatenate(cols).astype(np.float64))
    gt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    centres = torch.tensor(np.stack([T[:3, 3] for T in seq.poses])).float()
    normals = orient_towards(torch.tensor(np.asarray(gt.points)).float(), torch.tensor(np.asarray(gt.normals)).float(),
                             centres)
    gt.normals = o3d.utility.Vector3dVector(normals.numpy().astype(np.float64))
    return SimpleNamespace(seq=seq, frames=frames, gt=gt)


@pytest.fixture(scope="module")
def rec(scene):
    """A map of the room built by the Reconstructor: dense depth seeding (growth ablated), one update per frame."""
    cfg = eo3d.Config(ablate=("growth",))
    cfg.depth_scale = scene.seq.depth_scale
    cfg.seeding.pixel_stride = 4
    r = eo3d.Reconstructor(scene.seq.intrinsic, "cpu", cfg)
    for f in scene.frames:
        r.integrate(f, updates=1)
    return r


def _distances(a: o3d.geometry.PointCloud, b: o3d.geometry.PointCloud) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(a.compute_point_cloud_distance(b)), np.asarray(b.compute_point_cloud_distance(a))


def _nearest(gt: o3d.geometry.PointCloud, points: np.ndarray) -> np.ndarray:
    tree = o3d.geometry.KDTreeFlann(gt)
    return np.array([tree.search_knn_vector_3d(p, 1)[1][0] for p in points])


def test_point_cloud_matches_the_room(scene, rec):
    pcd = extract_point_cloud(rec.gmap, min_opacity=0.1, poses=scene.seq.poses)
    n = len(pcd.points)
    assert n == int((rec.gmap.opacities >= 0.1).sum()) > 1000
    assert pcd.has_colors() and pcd.has_normals()
    to_gt, from_gt = _distances(pcd, scene.gt)
    # centres sit on the observed surfaces (seeded from exact depth, moved by a few updates); the surface is
    # covered at the seeding spacing (4 px at 80x60 is ~15 cm at 2.5 m)
    assert to_gt.mean() < 0.01 and np.percentile(to_gt, 90) < 0.02, to_gt.mean()
    assert from_gt.mean() < 0.07, from_gt.mean()
    near = _nearest(scene.gt, np.asarray(pcd.points))
    colour_err = np.abs(np.asarray(pcd.colors) - np.asarray(scene.gt.colors)[near]).mean()
    assert colour_err < 0.08, colour_err
    assert np.asarray(pcd.colors).min() >= 0.0 and np.asarray(pcd.colors).max() <= 1.0
    # seeds are isotropic, so their normals come from the local plane fit, oriented toward the cameras
    dots = (np.asarray(pcd.normals) * np.asarray(scene.gt.normals)[near]).sum(1)
    assert (dots > 0.8).mean() > 0.9 and (dots < 0).mean() < 0.05, ((dots > 0.8).mean(), (dots < 0).mean())
    # the opacity filter
    assert len(extract_point_cloud(rec.gmap, min_opacity=0.999, normals="none").points) < n


def test_point_cloud_normals_are_the_shortest_axis():
    """Flat Gaussians: the normal is the axis of the smallest scale, flipped toward the camera."""
    g = GaussianMap(0)
    n = 40
    axis_angle = torch.rand(n, 3) * 2 - 1
    quats = torch.cat([torch.ones(n, 1), 0.8 * axis_angle], 1)  # wxyz, unnormalised on purpose
    means = torch.randn(n, 3) * 0.2
    g.add(means, torch.rand(n, 3), torch.tensor([[0.05, 0.04, 0.004]]).expand(n, 3), 0.9, quats)
    pcd = extract_point_cloud(g, poses=[np.eye(4)], normals="auto")
    from eligsir_o3d.render.projection import quat_to_rotmat as quat_to_rotmats

    z_axes = quat_to_rotmats(quats)[:, :, 2].numpy()
    normals = np.asarray(pcd.normals)
    np.testing.assert_allclose(np.abs((normals * z_axes).sum(1)), 1.0, atol=1e-5)
    to_cam = -means.numpy()  # the camera sits at the origin
    assert ((normals * to_cam).sum(1) >= 0).all()
    torch.testing.assert_close(torch.tensor(np.asarray(pcd.colors)).float(),
                               sh0_to_rgb(g.params["sh0"][:, 0]).clamp(0, 1).detach())


def test_mesh_conventions_on_exact_depth(scene):
    """TSDF fusion of the room's exact ray-cast depth: checks intrinsics, pose direction (world-to-camera
    extrinsic) and colour, independent of map quality. A swapped pose convention gives 0.2-0.7 m errors."""
    def exact(camera, T):
        color, depth = scene.seq.render(T, camera)
        return SimpleNamespace(color=torch.from_numpy(color), depth=torch.from_numpy(depth),
                               alpha=torch.from_numpy((depth > 0).astype(np.float32)))

    mesh = extract_triangle_mesh(exact, scene.seq.poses, scene.seq.camera, voxel_size=0.03)
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors() and mesh.has_vertex_normals()
    to_gt, from_gt = _distances(mesh.sample_points_uniformly(20000), scene.gt)
    assert to_gt.mean() < 0.03 and from_gt.mean() < 0.05, (to_gt.mean(), from_gt.mean())
    v = np.asarray(mesh.vertices)[::10]
    colour_err = np.abs(np.asarray(mesh.vertex_colors)[::10] - np.asarray(scene.gt.colors)[_nearest(scene.gt, v)])
    assert colour_err.mean() < 0.06, colour_err.mean()


def test_mesh_of_the_map_matches_the_room(scene, rec):
    """Mesh of the Reconstructor's map (rendered depth -> TSDF). Bounds: 14 cm mean, 13 cm median to the surface,
    18 cm mean from it, at 80x60 and 3 cm voxels (measured 11.1, 10.8 and 14.3 cm; exact depth gives 2.3 and 4.3 cm,
    a swapped pose convention 74 and 100 cm): the expected depth of a barely trained map (12 updates) of
    overlapping isotropic splats is biased toward the camera by centimetres, more so drawn at 80x60 with the
    low-pass of the 20x15 images it was supervised at (GaussianMap.low_pass; 3DGS's fixed 0.3 px^2 gave 6.0, 5.6
    and 8.1 cm here, while on the 7-Scenes kitchen the low-pass lowered held-out depth RMSE from 10.6 to 9.4 cm)."""
    mesh = extract_triangle_mesh(lambda cam, T: rec.render(T, cam), scene.seq.poses, rec.camera, voxel_size=0.03)
    assert len(mesh.triangles) > 1000
    to_gt, from_gt = _distances(mesh.sample_points_uniformly(20000), scene.gt)
    assert to_gt.mean() < 0.14 and np.median(to_gt) < 0.13, (to_gt.mean(), np.median(to_gt))
    assert from_gt.mean() < 0.18, from_gt.mean()


def test_mesh_needs_views_and_valid_poses():
    def never(camera, T):
        raise AssertionError("must not render")

    with pytest.raises(ValueError, match="at least one pose"):
        extract_triangle_mesh(never, [], eo3d.Camera(8, 8, 8, 8, 3.5, 3.5))
    with pytest.raises(ValueError, match="mesh view 1: pose.*non-rigid"):
        extract_triangle_mesh(never, [np.eye(4), np.diag([2.0, 1, 1, 1])], eo3d.Camera(8, 8, 8, 8, 3.5, 3.5))


def _random_map(degree: int, n: int = 50) -> GaussianMap:
    g = GaussianMap(degree)
    g.add(torch.randn(n, 3), torch.rand(n, 3), torch.rand(n, 3) * 0.1 + 0.01, torch.rand(n) * 0.9 + 0.05,
          torch.randn(n, 4))
    with torch.no_grad():
        g.params["shN"].copy_(torch.randn_like(g.params["shN"]))
    return g


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip_plyfile_and_open3d(tmp_path, degree):
    from plyfile import PlyData

    g = _random_map(degree)
    p = {k: v.detach().numpy() for k, v in g.params.items()}
    path = save_ply(g, tmp_path / "map.ply")
    k = (degree + 1) ** 2 - 1

    v = PlyData.read(str(path))["vertex"]
    col = lambda *names: np.stack([np.asarray(v[n]) for n in names], -1)  # noqa: E731
    names = v.data.dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert len([f for f in names if f.startswith("f_rest_")]) == 3 * k  # the SH degree, as 3DGS records it
    np.testing.assert_array_equal(col("x", "y", "z"), p["means"])
    np.testing.assert_array_equal(col("f_dc_0", "f_dc_1", "f_dc_2"), p["sh0"][:, 0])
    if k:
        rest = col(*[f"f_rest_{i}" for i in range(3 * k)])
        np.testing.assert_array_equal(rest.reshape(-1, 3, k).transpose(0, 2, 1), p["shN"])  # channel-major
    np.testing.assert_array_equal(np.asarray(v["opacity"]), p["opacities"])  # logit
    np.testing.assert_array_equal(col("scale_0", "scale_1", "scale_2"), p["scales"])  # log
    np.testing.assert_array_equal(col("rot_0", "rot_1", "rot_2", "rot_3"), p["quats"])  # wxyz

    # Open3D 0.20 recognises the 3DGS layout: f_rest as [N, K, 3], scales activated (exp), the rest raw
    pc = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(pc.point.positions.numpy(), p["means"])
    np.testing.assert_array_equal(pc.point["f_dc"].numpy(), p["sh0"][:, 0])
    np.testing.assert_array_equal(pc.point["opacity"].numpy()[:, 0], p["opacities"])
    np.testing.assert_array_equal(pc.point["rot"].numpy(), p["quats"])
    np.testing.assert_allclose(pc.point["scale"].numpy(), np.exp(p["scales"]), rtol=1e-6)
    if k:
        np.testing.assert_array_equal(pc.point["f_rest"].numpy(), p["shN"])
    else:
        assert "f_rest" not in pc.point

    back = load_ply(path)
    assert back.sh_degree == degree
    for name in p:
        np.testing.assert_array_equal(back.params[name].detach().numpy(), p[name])


def test_export_from_ply_with_trajectory_and_sphere_views(tmp_path, scene, rec):
    folder = tmp_path / "run"
    rec.save_ply(folder / "map.ply")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for i, T in enumerate(scene.seq.poses[::2]):
        t, q = pose_to_tum(T)
        lines.append(f"{i / 15:.6f} " + " ".join(f"{x:.7f}" for x in (*t, *q)))
    (folder / "trajectory.txt").write_text("\n".join(lines) + "\n")
    c = scene.seq.camera
    (folder / "config.json").write_text(json.dumps({"camera": {"width": c.width, "height": c.height, "fx": c.fx,
                                                               "fy": c.fy, "cx": c.cx, "cy": c.cy}}))
    s = export_from_ply(folder / "map.ply", mesh_path=tmp_path / "out" / "mesh.ply",
                        cloud_path=tmp_path / "out" / "cloud.ply", voxel_size=0.05, render_scale=1.0)
    assert s["view_source"].endswith("trajectory.txt") and s["views"] == N_FRAMES // 2
    assert s["camera"]["width"] == W
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "out" / "mesh.ply"))
    cloud = o3d.io.read_point_cloud(str(tmp_path / "out" / "cloud.ply"))
    assert len(mesh.triangles) == s["triangles"] > 100 and len(cloud.points) == s["points"] > 1000
    assert cloud.has_normals() and cloud.has_colors()
    assert not list((tmp_path / "out").glob(".*tmp*"))

    s = export_from_ply(folder / "map.ply", cloud_path=tmp_path / "given.ply", poses=folder / "trajectory.txt")
    assert s["view_source"] == str(folder / "trajectory.txt") and s["views"] == N_FRAMES // 2

    poses, depth_needed = sphere_poses(np.asarray(cloud.points), c, n_views=6)
    assert len(poses) == 6 and depth_needed > 0
    s = export_from_ply(folder / "map.ply", cloud_path=tmp_path / "sphere.ply", views="sphere")
    assert s["view_source"] == "sphere" and s["views"] == 40

    with pytest.raises(ValueError, match="nothing to export"):
        export_from_ply(folder / "map.ply")
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(PlyError, match="bad.ply.*missing vertex properties"):
        export_from_ply(tmp_path / "bad.ply", cloud_path=tmp_path / "c.ply")
