"""Geometry export: a coloured point cloud of the Gaussian centres, and a triangle mesh by TSDF fusion of depth
and colour rendered from the map (Open3D's VoxelBlockGrid, then marching cubes).

    pcd = extract_point_cloud(rec.gmap, min_opacity=0.1, poses=poses)          # o3d.geometry.PointCloud
    mesh = extract_triangle_mesh(render_fn, poses, camera, voxel_size=0.02)      # o3d.geometry.TriangleMesh
    export_from_ply("runs/kitchen/map.ply", mesh_path="mesh.ply", cloud_path="cloud.ply")   # `eligsir export`

Poses are ``T_world_cam`` (camera-to-world); the only place Open3D's world-to-camera ``extrinsic`` appears is the
VoxelBlockGrid call in :func:`extract_triangle_mesh`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import open3d as o3d
import torch

from ..core.camera import Camera, check_pose, invert_pose
from ..core.gaussians import GaussianMap, sh0_to_rgb
from ..render.projection import quat_to_rotmat  # columns are the Gaussians' axes

log = logging.getLogger("eligsir_o3d")

# ---- point cloud ---------------------------------------------------------------------------------------
@torch.no_grad()
def extract_point_cloud(gmap: GaussianMap, min_opacity: float = 0.1, poses: Sequence[np.ndarray] | None = None,
                        normals: str = "auto", flat_ratio: float = 0.5, knn: int = 16) -> o3d.geometry.PointCloud:
    """The Gaussian centres with opacity >= ``min_opacity`` as a coloured Open3D point cloud.

    Colour: the SH DC term (the view-independent colour), clamped to [0, 1]. Normals (``normals``):
    - ``"auto"``: the shortest axis of each flat Gaussian (smallest scale < ``flat_ratio`` x the middle one, the
      axis a surface-aligned splat points along); near-isotropic Gaussians have no such axis, so theirs come from
      a local plane fit of their ``knn`` nearest centres (Open3D's ``estimate_normals``);
    - ``"axis"``: the shortest axis for every Gaussian; ``"pca"``: the plane fit for every point; ``"none"``.
    With ``poses`` (camera-to-world [4, 4]), each normal is flipped to face the nearest camera centre, so normals
    point out of the observed surface (what Poisson reconstruction and shading expect).
    """
    if normals not in ("auto", "axis", "pca", "none"):
        raise ValueError(f"normals must be 'auto', 'axis', 'pca' or 'none', got {normals!r}")
    if not 0.0 <= min_opacity < 1.0:
        raise ValueError(f"min_opacity must be in [0, 1), got {min_opacity}")
    keep = gmap.opacities >= min_opacity  # [N]
    means = gmap.means[keep].detach().float().cpu()  # [M, 3]
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(means.numpy().astype(np.float64))
    rgb = sh0_to_rgb(gmap.params["sh0"][keep, 0]).clamp(0.0, 1.0).float().cpu()  # [M, 3]
    pcd.colors = o3d.utility.Vector3dVector(rgb.numpy().astype(np.float64))
    m = means.shape[0]
    if normals == "none" or m == 0:
        return pcd
    scales = gmap.scales[keep].detach().float().cpu()  # [M, 3]
    axes = quat_to_rotmat(gmap.quats[keep].detach().float().cpu())  # [M, 3, 3]
    sorted_scales, order = torch.sort(scales, dim=1)
    shortest = torch.gather(axes, 2, order[:, None, :1].expand(m, 3, 1))[..., 0]  # [M, 3]
    flat = sorted_scales[:, 0] < flat_ratio * sorted_scales[:, 1]  # [M]
    if normals == "axis":
        n = shortest
    else:
        n = torch.zeros(m, 3)
        need_fit = torch.ones(m, dtype=torch.bool) if normals == "pca" else ~flat
        if need_fit.any() and m >= 3:
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(min(knn, m)))
            fitted = torch.from_numpy(np.asarray(pcd.normals)).float()
            n[need_fit] = fitted[need_fit]
        if normals == "auto":
            n[flat] = shortest[flat]
    if poses is not None and len(poses) > 0:
        centres = torch.from_numpy(np.stack([check_pose(T, f"pose {i}")[:3, 3] for i, T in enumerate(poses)])).float()
        n = orient_towards(means, n, centres)
    pcd.normals = o3d.utility.Vector3dVector(n.numpy().astype(np.float64))
    return pcd


def orient_towards(points: torch.Tensor, normals: torch.Tensor, centres: torch.Tensor,
                   chunk: int = 65536) -> torch.Tensor:
    """Flip each normal [M, 3] so that it faces the nearest of the camera ``centres`` [P, 3]."""
    out = normals.clone()
    for s in range(0, points.shape[0], chunk):
        p = points[s:s + chunk]
        nearest = torch.cdist(p, centres).argmin(1)  # [c]
        facing = ((centres[nearest] - p) * out[s:s + chunk]).sum(1)
        out[s:s + chunk][facing < 0] *= -1.0
    return out


# ---- triangle mesh -------------------------------------------------------------------------------------
@torch.no_grad()
def extract_triangle_mesh(render_fn: Callable, poses: Sequence[np.ndarray], camera: Camera,
                          voxel_size: float = 0.02, depth_max: float = 5.0, sdf_trunc: float | None = None,
                          alpha_min: float = 0.5, device: str = "CPU:0", weight_threshold: float = 1.0,
                          block_count: int = 20000) -> o3d.geometry.TriangleMesh:
    """TSDF fusion of depth and colour rendered from the map at ``poses``, then marching cubes.

    render_fn(camera, T_world_cam) -> RenderOutput (colour [H, W, 3], z-depth [H, W] metres, alpha [H, W]).
    Pixels with accumulated opacity below ``alpha_min`` are not integrated (their expected depth blends the
    surface with the background). ``sdf_trunc`` (metres) defaults to 4 voxels. ``device`` is an Open3D device
    string ("CPU:0", "CUDA:0"). Returns a legacy mesh with vertex colours and normals (empty if nothing was seen).
    """
    if not voxel_size > 0 or not depth_max > 0:
        raise ValueError(f"voxel_size and depth_max must be positive, got {voxel_size} and {depth_max}")
    if len(poses) == 0:
        raise ValueError("extract_triangle_mesh needs at least one pose to render the map from")
    poses = [check_pose(T, f"mesh view {i}: pose") for i, T in enumerate(poses)]
    trunc = 4.0 * voxel_size if sdf_trunc is None else float(sdf_trunc)
    if not trunc > 0:
        raise ValueError(f"sdf_trunc must be positive, got {sdf_trunc}")
    dev = o3d.core.Device(device)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
        attr_channels=((1,), (1,), (3,)), voxel_size=float(voxel_size), block_resolution=16,
        block_count=int(block_count), device=dev)
    intrinsic = o3d.core.Tensor(camera.K, o3d.core.float64)
    integrated = 0
    for i, T in enumerate(poses):
        out = render_fn(camera, T)
        alpha = out.alpha.detach().float()
        depth = torch.where(alpha >= alpha_min, out.depth.detach().float(), torch.zeros_like(alpha))
        depth = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0)
        if not (depth > 0).any():
            continue
        color = out.color.detach().float().clamp(0.0, 1.0)
        depth_img = o3d.t.geometry.Image(o3d.core.Tensor(depth.cpu().numpy()[..., None].copy())).to(dev)
        color_img = o3d.t.geometry.Image(o3d.core.Tensor(color.cpu().numpy().copy())).to(dev)
        extrinsic = o3d.core.Tensor(invert_pose(T), o3d.core.float64)  # Open3D wants world-to-camera
        blocks = vbg.compute_unique_block_coordinates(depth_img, intrinsic, extrinsic, 1.0, float(depth_max),
                                                      trunc / voxel_size)
        vbg.integrate(blocks, depth_img, color_img, intrinsic, extrinsic, 1.0, float(depth_max), trunc / voxel_size)
        integrated += 1
    if integrated == 0:
        log.warning("extract_triangle_mesh: the map rendered no depth with alpha >= %.2f at any of %d views",
                    alpha_min, len(poses))
        return o3d.geometry.TriangleMesh()
    mesh = vbg.extract_triangle_mesh(weight_threshold=float(weight_threshold)).to_legacy()
    if mesh.has_vertex_colors():  # a weighted mean of colours in [0, 1] can round a hair past 1
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
    mesh.compute_vertex_normals()
    return mesh


# ---- a saved map ---------------------------------------------------------------------------------------
def export_from_ply(map_ply: str | Path, mesh_path: str | Path | None = None, cloud_path: str | Path | None = None,
                    poses: Sequence[np.ndarray] | str | Path | None = None, camera: Camera | None = None,
                    voxel_size: float = 0.02, depth_max: float = 5.0, min_opacity: float = 0.1,
                    render_scale: float = 0.5, max_views: int = 150, renderer: str = "auto",
                    device: str = "cpu", views: str = "auto") -> dict:
    """Mesh and/or point cloud of a saved 3DGS PLY (what ``eligsir export`` runs). Returns a summary dict.

    Viewpoints for the mesh (and for orienting the cloud's normals), first match wins:
    1. ``poses``: a list of camera-to-world [4, 4] or a TUM trajectory file;
    2. ``trajectory.txt`` beside the map (the results folder of ``eligsir map``), subsampled to ``max_views``:
       the views the map was built from, from inside the scene;
    3. ``views="sphere"`` or nothing else available: ``n`` cameras on a sphere around the map's bounding box,
       looking inward (right for objects; inside a room they see the walls' backs, hence the order).
    Camera: ``camera``, else the one in a ``config.json``/``intrinsics.json`` beside the map, else 640x480 with
    fx = fy = 525; the mesh views are rendered at ``render_scale`` of it (half resolution already samples a
    surface 3 m away every 1.1 cm, finer than the default 2 cm voxels).
    """
    from ..datasets.base import read_tum_trajectory
    from ..io.guards import check_tsdf_memory, refuse_overwriting_inputs
    from ..io.ply import load_ply
    from ..render import get_renderer, render_map
    from .views import DEFAULT_CAMERA, camera_next_to, sphere_poses, subsample

    map_ply = Path(map_ply)
    if mesh_path is None and cloud_path is None:
        raise ValueError("nothing to export: give a mesh path and/or a point-cloud path")
    refuse_overwriting_inputs({"--mesh": mesh_path, "--point-cloud": cloud_path},
                              {"the map": map_ply, "--poses": poses if isinstance(poses, (str, Path)) else None,
                               "trajectory.txt": map_ply.parent / "trajectory.txt",
                               "config.json": map_ply.parent / "config.json"})
    check_geometry_path(mesh_path, "--mesh", MESH_SUFFIXES)
    check_geometry_path(cloud_path, "--point-cloud", CLOUD_SUFFIXES)
    if views not in ("auto", "trajectory", "sphere"):
        raise ValueError(f"views must be 'auto', 'trajectory' or 'sphere', got {views!r}")
    gmap = load_ply(map_ply, device)
    if len(gmap) == 0:
        raise ValueError(f"{map_ply}: the map has no Gaussians")
    if mesh_path is not None:  # a tiny voxel would fill memory for minutes before failing
        check_tsdf_memory(gmap.means.detach().float().cpu().numpy(), voxel_size)
    camera = camera or camera_next_to(map_ply) or DEFAULT_CAMERA
    source = "given"
    if isinstance(poses, (str, Path)):
        source = str(poses)
        _, poses = read_tum_trajectory(Path(poses))
    if poses is None and views != "sphere" and (map_ply.parent / "trajectory.txt").is_file():
        _, poses = read_tum_trajectory(map_ply.parent / "trajectory.txt")
        source = str(map_ply.parent / "trajectory.txt")
    if views == "trajectory" and poses is None:
        raise ValueError(f"views='trajectory' but no poses were given and {map_ply.parent / 'trajectory.txt'} "
                         f"does not exist")
    summary: dict = {"map": str(map_ply), "gaussians": len(gmap), "camera": camera.__dict__.copy()}
    mesh_depth_max = depth_max
    if poses is None:
        poses, needed = sphere_poses(gmap.means.detach().cpu().numpy(), camera)
        mesh_depth_max = max(depth_max, needed)
        source = "sphere"
    poses = subsample([check_pose(T, f"view {i}: pose") for i, T in enumerate(poses)], max_views)
    summary["views"], summary["view_source"] = len(poses), source

    if cloud_path is not None:
        pcd = extract_point_cloud(gmap, min_opacity=min_opacity, poses=poses)
        _write(o3d.io.write_point_cloud, cloud_path, pcd)
        summary["cloud"], summary["points"] = str(cloud_path), len(pcd.points)
    if mesh_path is not None:
        rend = get_renderer(renderer, device)
        background = torch.zeros(3, device=gmap.device)

        def render_fn(cam: Camera, T: np.ndarray):
            return render_map(rend, gmap, cam, T, background)

        mesh = extract_triangle_mesh(render_fn, poses, camera.scaled(render_scale), voxel_size=voxel_size,
                                     depth_max=mesh_depth_max)
        _write(o3d.io.write_triangle_mesh, mesh_path, mesh)
        summary["mesh"], summary["vertices"], summary["triangles"] = \
            str(mesh_path), len(mesh.vertices), len(mesh.triangles)
    return summary


def _write(writer, path: str | Path, geometry) -> None:
    """Write with Open3D through a temporary file and an atomic rename (Open3D picks the format by suffix)."""
    from ..io.atomic import WriteFailed, commit_file, temp_for, write_failed

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_for(path, path.suffix or ".ply")  # a device node has no suffix: PLY into it
    except OSError as e:
        raise write_failed(path, e) from None
    try:
        if not writer(str(tmp), geometry):
            raise WriteFailed(path, "Open3D could not write it (folder not writable or disk full?)")
        commit_file(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")  # what Open3D writes a triangle mesh as
CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")  # and a point cloud


def check_geometry_path(path: str | Path | None, option: str, suffixes: tuple[str, ...]) -> None:
    """Refuse (ValueError) a file path whose suffix Open3D cannot write: it picks the format by the suffix (a
    device or FIFO gets PLY)."""
    from ..io.atomic import output_kind

    if path is not None and Path(path).suffix.lower() not in suffixes and output_kind(path) in ("new", "file"):
        raise ValueError(f"{option} {path}: the file name must end in {', '.join(suffixes)} (the format is chosen "
                         f"by it)")
