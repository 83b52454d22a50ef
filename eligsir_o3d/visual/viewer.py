"""A browser viewer of a Gaussian map on viser: splats, the trajectory's cameras, and the mesh / point cloud.

    viewer = MapViewer(host="127.0.0.1", port=8080)       # serves http://127.0.0.1:8080 at once
    viewer.set_splats(read_splats("runs/kitchen/map.ply"))
    viewer.set_trajectory(poses, camera)                    # frustums + one "go to camera" button each
    viewer.add_geometry("mesh", o3d.io.read_triangle_mesh("mesh.ply"))   # with a show/hide checkbox

``open_map_viewer(map.ply)`` does all of that for a results folder (what ``eligsir view`` runs); the live view
while mapping (:mod:`.live`) drives the same object. The browser draws the splats itself (WebGL), so the server
only sends them; viser is imported lazily (``pip install 'eligsir-o3d[view]'``).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.camera import Camera, rotmat_to_quat
from .splats import Splats

log = logging.getLogger("eligsir_o3d")

INSTALL_HINT = "the viewer needs viser: pip install 'eligsir-o3d[view]' (or pip install viser)"
GEOMETRY_NAMES = ("mesh.ply", "mesh.obj", "cloud.ply", "cloud.pcd", "point_cloud.ply", "points.ply")


def import_viser():
    try:
        import viser
    except ImportError:
        raise RuntimeError(INSTALL_HINT) from None
    return viser


def wxyz(T: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion of a pose's rotation: viser, like this package, uses OpenCV camera axes."""
    x, y, z, w = rotmat_to_quat(np.asarray(T, dtype=np.float64)[:3, :3])
    return np.array([w, x, y, z])


def up_direction(poses: Sequence[np.ndarray]) -> np.ndarray | None:
    """World 'up' as the cameras saw it (OpenCV y points down), or None without cameras."""
    if not len(poses):
        return None
    up = -np.mean([np.asarray(T)[:3, 1] for T in poses], axis=0)
    norm = float(np.linalg.norm(up))
    return up / norm if norm > 1e-6 else None


class MapViewer:
    """One viser server showing one map. Every ``set_*`` replaces what it set before (safe to call repeatedly)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, title: str = "eligsir map"):
        from .bind_check import check_bind

        viser = import_viser()
        check_bind(host, port)  # a bad port/host is one line here, not a thread traceback and a hang
        self.host = host
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = int(self.server.get_port())
        self.camera: Camera | None = None
        self.poses: list[np.ndarray] = []
        self.scene_size = 1.0
        self._handles: dict[str, object] = {}
        self._toggles: dict[str, object] = {}
        self._layers = self.server.gui.add_folder("Layers")
        self._cameras = None

    @property
    def url(self) -> str:
        from .bind_check import is_wildcard

        host = "127.0.0.1" if is_wildcard(self.host) else (f"[{self.host}]" if ":" in self.host else self.host)
        return f"http://{host}:{self.port}"

    @property
    def urls(self) -> list[str]:
        """Every URL it is served at (for --host 0.0.0.0: this machine's addresses too)."""
        from .bind_check import served_urls

        return served_urls(self.host, self.port)

    def close(self) -> None:
        try:
            self.server.stop()
        except RuntimeError:  # a server whose thread never started: nothing to stop
            pass

    # ---- layers ----------------------------------------------------------------------------------------
    def _layer(self, label: str, handle) -> None:
        """Remember ``handle`` under ``label``; the first time, add a checkbox that shows / hides it."""
        self._handles[label] = handle
        if label in self._toggles:
            handle.visible = bool(self._toggles[label].value)
            return
        with self._layers:
            box = self.server.gui.add_checkbox(label, initial_value=True)

        @box.on_update
        def _(_event) -> None:
            h = self._handles.get(label)
            if h is not None:
                h.visible = bool(box.value)

        self._toggles[label] = box

    def set_splats(self, splats: Splats) -> None:
        """Draw the Gaussians (replacing the previous ones)."""
        lo, hi = splats.bounds()
        self.scene_size = max(float(np.linalg.norm(hi - lo)), 1e-3)
        h = self.server.scene.add_gaussian_splats("/map/splats", centers=splats.centers,
                                                  covariances=splats.covariances, rgbs=splats.rgbs,
                                                  opacities=splats.opacities)
        self._layer("Gaussians", h)

    def add_geometry(self, label: str, geometry) -> None:
        """An Open3D TriangleMesh or PointCloud as a layer with a checkbox."""
        import open3d as o3d

        name = "/map/" + "".join(c if c.isalnum() else "_" for c in label)
        if isinstance(geometry, o3d.geometry.TriangleMesh):
            import trimesh  # installed with viser

            v = np.asarray(geometry.vertices, dtype=np.float32)
            f = np.asarray(geometry.triangles, dtype=np.int32)
            colors = (np.clip(np.asarray(geometry.vertex_colors), 0, 1) * 255).astype(np.uint8) \
                if geometry.has_vertex_colors() else None
            h = self.server.scene.add_mesh_trimesh(name, trimesh.Trimesh(v, f, vertex_colors=colors, process=False))
        elif isinstance(geometry, o3d.geometry.PointCloud):
            pts = np.asarray(geometry.points, dtype=np.float32)
            colors = (np.asarray(geometry.colors, dtype=np.float32) if geometry.has_colors()
                      else np.full_like(pts, 0.7))
            h = self.server.scene.add_point_cloud(name, pts, colors, point_size=0.004 * self.scene_size,
                                                  point_shape="circle")
        else:
            raise TypeError(f"add_geometry: {label} is a {type(geometry).__name__}, not a TriangleMesh or PointCloud")
        self._layer(label, h)

    # ---- cameras ---------------------------------------------------------------------------------------
    def _frustum(self, name: str, T: np.ndarray, camera: Camera, color, scale: float, image=None):
        fov = 2.0 * math.atan(camera.height / (2.0 * camera.fy))
        return self.server.scene.add_camera_frustum(name, fov=fov, aspect=camera.width / camera.height,
                                                    scale=scale, thickness=1.5, thickness_units="screen",
                                                    color=color, image=image,
                                                    wxyz=wxyz(T), position=np.asarray(T)[:3, 3])

    def set_trajectory(self, poses: Sequence[np.ndarray], camera: Camera, max_cameras: int = 40,
                       labels: Sequence[str] | None = None) -> None:
        """The camera path as a line, up to ``max_cameras`` frustums spread along it, and a button per frustum
        that moves the browser's camera there (clicking a frustum does the same)."""
        self.camera, self.poses = camera, [np.asarray(T, dtype=np.float64) for T in poses]
        if not self.poses:
            return
        up = up_direction(self.poses)
        if up is not None:
            self.server.scene.set_up_direction(up)
        centres = np.stack([T[:3, 3] for T in self.poses])
        if len(centres) > 1:
            path = self.server.scene.add_line_segments("/trajectory/path", np.stack([centres[:-1], centres[1:]], 1),
                                                       colors=(230, 120, 30), thickness=2.0,
                                                       thickness_units="screen")
            self._layer("Trajectory", path)
        pick = np.unique(np.linspace(0, len(self.poses) - 1, min(max_cameras, len(self.poses))).round().astype(int))
        scale = 0.012 * self.scene_size
        if self._cameras is not None:
            self._cameras.remove()
        self._cameras = self.server.gui.add_folder("Go to camera", expand_by_default=False)
        frustums = []
        for k in pick:
            T = self.poses[k]
            label = labels[k] if labels is not None else f"camera {k}"
            fr = self._frustum(f"/trajectory/cam_{k:06d}", T, camera, (30, 90, 220), scale)
            fr.on_click(lambda event, T=T: self.go_to(event.client, T))
            with self._cameras:
                button = self.server.gui.add_button(label)
            button.on_click(lambda event, T=T: self.go_to(event.client, T))
            frustums.append(fr)
        self._layer("Cameras", _Group(frustums))

    def go_to(self, client, T: np.ndarray) -> None:
        """Move one browser's camera to pose ``T`` (camera-to-world), looking where that camera looked."""
        if client is None:
            return
        T = np.asarray(T, dtype=np.float64)
        with client.atomic():
            client.camera.position = T[:3, 3]
            client.camera.look_at = T[:3, 3] + T[:3, 2] * 0.25 * self.scene_size
            client.camera.up_direction = -T[:3, 1]
            if self.camera is not None:
                client.camera.fov = 2.0 * math.atan(self.camera.height / (2.0 * self.camera.fy))

    def set_start_view(self, splats: Splats, T: np.ndarray | None = None, camera: Camera | None = None) -> None:
        """Where a newly opened page looks from: just behind the camera ``T`` if given (the first of the
        trajectory), else from outside the map's bounds toward its centre."""
        lo, hi = splats.bounds()
        centre = (lo + hi) / 2.0
        ic = self.server.initial_camera
        if camera is not None:
            ic.fov = 2.0 * math.atan(camera.height / (2.0 * camera.fy))
        if T is not None:
            T = np.asarray(T, dtype=np.float64)
            ahead = max(float(np.dot(centre - T[:3, 3], T[:3, 2])), 0.1 * self.scene_size)
            # a step behind and above that camera, so that its own frustum is in view rather than around the eye
            ic.position = T[:3, 3] - T[:3, 2] * 0.15 * self.scene_size - T[:3, 1] * 0.05 * self.scene_size
            ic.look_at = T[:3, 3] + T[:3, 2] * ahead
            ic.up = -T[:3, 1]
        else:
            ic.position = centre + np.array([0.6, 0.6, 0.6]) * self.scene_size
            ic.look_at = centre


class _Group:
    """Several scene handles shown / hidden together (one checkbox for all frustums)."""

    def __init__(self, handles: list):
        self.handles = handles
        self._visible = True

    @property
    def visible(self) -> bool:
        return self._visible

    @visible.setter
    def visible(self, value: bool) -> None:
        self._visible = bool(value)
        for h in self.handles:
            h.visible = self._visible


def find_geometry(map_ply: Path) -> dict[str, Path]:
    """Meshes and point clouds exported beside a map (``eligsir export``'s usual names), by layer label."""
    found = {}
    for name in GEOMETRY_NAMES:
        p = map_ply.parent / name
        if p.is_file() and p.resolve() != map_ply.resolve():
            found.setdefault("Mesh" if name.startswith("mesh") else "Point cloud", p)
    return found


def read_geometry(path: Path):
    """An Open3D mesh (if the file has triangles) or point cloud; ValueError naming the file if it is neither."""
    import open3d as o3d

    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) > 0:
        return mesh
    pcd = o3d.io.read_point_cloud(str(path))
    if len(pcd.points) > 0:
        return pcd
    raise ValueError(f"{path}: neither a triangle mesh nor a point cloud Open3D can read")


def open_map_viewer(map_ply: str | Path, host: str = "127.0.0.1", port: int = 8080,
                    trajectory: str | Path | None = None, mesh: str | Path | None = None,
                    point_cloud: str | Path | None = None, max_cameras: int = 40) -> MapViewer:
    """Serve ``map_ply`` (any 3DGS PLY) with the trajectory, mesh and point cloud found beside it or given."""
    from ..export.views import DEFAULT_CAMERA, camera_next_to
    from ..pose.trajectory import read_tum_trajectory
    from .splats import read_splats

    map_ply = Path(map_ply)
    splats = read_splats(map_ply)
    traj = Path(trajectory) if trajectory is not None else map_ply.parent / "trajectory.txt"
    poses: list[np.ndarray] = []
    if traj.is_file() or trajectory is not None:
        _, poses = read_tum_trajectory(traj)
    layers = find_geometry(map_ply)
    if mesh is not None:
        layers["Mesh"] = Path(mesh)
    if point_cloud is not None:
        layers["Point cloud"] = Path(point_cloud)
    geometry = {label: read_geometry(p) for label, p in layers.items()}  # fail before the server starts
    camera = camera_next_to(map_ply) or DEFAULT_CAMERA
    viewer = MapViewer(host, port, title=f"{map_ply.parent.name}/{map_ply.name}")
    viewer.set_splats(splats)
    for label, g in geometry.items():
        viewer.add_geometry(label, g)
        viewer._handles[label].visible = False  # the splats are the map; the rest is one click away
        viewer._toggles[label].value = False
    if poses:
        viewer.set_trajectory(poses, camera, max_cameras)
    viewer.set_start_view(splats, poses[0] if poses else None, camera)
    log.info("viewer: %d Gaussians (SH degree %d), %d cameras, layers %s", len(splats), splats.sh_degree,
             len(poses), ", ".join(geometry) or "none")
    return viewer
