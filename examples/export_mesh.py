"""A saved map (map.ply from eligsir map or rec.save_ply) to a triangle mesh and a point cloud; show them.

    python examples/export_mesh.py runs/kitchen/map.ply --out runs/kitchen
    python examples/export_mesh.py runs/kitchen/map.ply --no-show

The mesh is a TSDF fusion (Open3D VoxelBlockGrid) of depth rendered from the map at the trajectory.txt poses
beside it; the point cloud is the Gaussians' centres with their colour. The viewer opens only when a display
exists (and not with --no-show).
"""

import argparse
import os
from pathlib import Path

import open3d as o3d

from eligsir_o3d.export import export_from_ply

ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("map_ply", type=Path)
ap.add_argument("--out", type=Path, default=None, help="folder for mesh.ply and cloud.ply (default: beside the map)")
ap.add_argument("--voxel-size", type=float, default=0.02, help="TSDF voxel size (m)")
ap.add_argument("--max-views", type=int, default=150, help="at most this many viewpoints are rendered and fused")
ap.add_argument("--no-show", action="store_true")
args = ap.parse_args()

out = args.out or args.map_ply.parent
out.mkdir(parents=True, exist_ok=True)
summary = export_from_ply(args.map_ply, out / "mesh.ply", out / "cloud.ply", voxel_size=args.voxel_size,
                          max_views=args.max_views)
for key, value in summary.items():
    print(f"{key}: {value}")

mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
cloud = o3d.io.read_point_cloud(str(out / "cloud.ply"))
mesh.compute_vertex_normals()
print(f"mesh: {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles; cloud: {len(cloud.points)} points")
if not args.no_show and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    o3d.visualization.draw_geometries([mesh], window_name="eligsir mesh")
    o3d.visualization.draw_geometries([cloud], window_name="eligsir point cloud")
