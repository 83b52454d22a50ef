"""A map out of the package, one module a kind of output:

- :mod:`.geometry`: Open3D geometry, a coloured point cloud of the Gaussian centres and a triangle mesh by TSDF
  fusion of rendered depth (``eligsir export --mesh/--point-cloud``);
- :mod:`.viewers`: a 3DGS PLY for viewers with 3DGS's fixed low-pass, the map's own low-pass baked in
  (``--for-viewers``);
- :mod:`.web`: SPZ and ``.splat`` for web players, written from the map in memory (``--spz/--splat``);
- :mod:`.views`: where a saved map is seen from (the camera and poses beside it, or a sphere of cameras).

The standard 3DGS PLY itself is :func:`eligsir_o3d.io.ply.save_ply`.

    from eligsir_o3d.export import export_from_ply, write_web
    export_from_ply("runs/kitchen/map.ply", mesh_path="mesh.ply", cloud_path="cloud.ply")
"""

from .geometry import export_from_ply, extract_point_cloud, extract_triangle_mesh
from .viewers import baked_for_viewers, for_viewers, write_for_viewers
from .web import write_web

__all__ = ["baked_for_viewers", "export_from_ply", "extract_point_cloud", "extract_triangle_mesh", "for_viewers",
           "write_for_viewers", "write_web"]
