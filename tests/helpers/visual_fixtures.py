"""Small maps for the viewer, picture and video tests: a coloured wall 2 m in front of a short camera path."""

import threading
from pathlib import Path

import numpy as np

from eligsir_o3d.core.gaussians import SH_C0
from eligsir_o3d.pose.trajectory import write_tum_trajectory


def wall_colors(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[N, 3] RGB of the wall at (u, v) in [0, 1]^2: red grows to the right, green downwards, a little blue."""
    return np.stack([0.15 + 0.8 * u, 0.15 + 0.8 * v, np.full_like(u, 0.3)], 1)


def write_path(folder: Path, n: int = 8) -> Path:
    poses = []
    for k in range(n):
        T = np.eye(4)
        T[0, 3] = -0.1 + 0.2 * k / max(n - 1, 1)
        poses.append(T)
    return write_tum_trajectory(folder / "trajectory.txt", np.arange(n) / 30.0, poses)


def write_third_party_ply(path: Path, nx: int = 48, ny: int = 36, sh_degree: int = 3) -> tuple[Path, dict]:
    """A 3DGS PLY as the original 3DGS code and gsplat's exporter write it (property order, SH degree 3, no
    comments, nothing from this package): a wall of nx * ny Gaussians at z = 2 m; Gaussian 0 is rotated 90
    degrees about z and anisotropic. Returns (path, the raw property arrays)."""
    from plyfile import PlyData, PlyElement

    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    u, v = u.ravel(), v.ravel()
    n = u.size
    raw = {"x": -1.2 + 2.4 * u, "y": -0.9 + 1.8 * v, "z": np.full(n, 2.0)}
    raw.update(nx=np.zeros(n), ny=np.zeros(n), nz=np.zeros(n))
    dc = (wall_colors(u, v) - 0.5) / SH_C0
    for i in range(3):
        raw[f"f_dc_{i}"] = dc[:, i]
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    rest = 0.05 * rng.standard_normal((n, n_rest))
    for i in range(n_rest):
        raw[f"f_rest_{i}"] = rest[:, i]
    raw["opacity"] = np.full(n, 3.0)  # logit: ~0.95
    for i, s in enumerate((0.04, 0.04, 0.01)):
        raw[f"scale_{i}"] = np.full(n, np.log(s))
    raw["scale_0"][0], raw["scale_1"][0] = np.log(0.1), np.log(0.02)
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    q[0] = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]
    for i in range(4):
        raw[f"rot_{i}"] = q[:, i]
    arr = np.empty(n, dtype=[(k, "f4") for k in raw])
    for k, col in raw.items():
        arr[k] = col
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    return path, {k: arr[k].astype(np.float64) for k in raw}


def write_wall_map(folder: Path, sh_degree: int = 3) -> tuple[Path, Path]:
    """``folder/map.ply`` (the third-party wall) and ``folder/trajectory.txt`` beside it."""
    folder.mkdir(parents=True, exist_ok=True)
    map_ply, _ = write_third_party_ply(folder / "map.ply", sh_degree=sh_degree)
    return map_ply, write_path(folder)


class ViewerConnection:
    """A viewer page's websocket connection without the page: it reports a camera, as a browser does on load
    (viser counts a client from then on), and receives and discards everything the server sends."""

    def __init__(self, url: str):
        import msgspec
        import viser
        from websockets.sync.client import connect

        self.ws = connect(url.replace("http", "ws", 1), subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, open_timeout=10)
        self.ws.send(msgspec.msgpack.encode({
            "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, -1.0],
            "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
            "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, -1.0, 0.0]}))
        self.received = 0
        self.thread = threading.Thread(target=self._drain, daemon=True)
        self.thread.start()

    def _drain(self) -> None:
        try:
            for msg in self.ws:
                self.received += len(msg)
        except Exception:  # closed
            pass

    def close(self) -> None:
        self.ws.close()
        self.thread.join(5)
