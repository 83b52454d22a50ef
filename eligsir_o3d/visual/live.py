"""Live view while mapping (``eligsir map ... --view``): the viewer page of :mod:`.viewer`, fed from the mapping
thread with the current splats, the current camera (with its image) and the path so far.

    live = LiveView(port=8080)             # serves at once; live.url
    live.attach(rec)                       # a Reconstructor callback: runs after every update
    live.observe(frame)                    # each released frame: the current camera
    ...                                    # mapping
    live.show_results("runs/x")            # afterwards: the saved map with its cameras, as `eligsir view` shows it

Cost control: the callback returns at once unless ``every_s`` seconds have passed since the last push AND a
browser is connected (a page that opens later gets the map at the next update). Its time is callback time, which
the Reconstructor books as excluded (not mapping time, not on the real-time clock), like evaluation; the viser
server thread that sends the data runs beside the mapper and is what the measured slowdown contains.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from .splats import splats_from_map
from .viewer import MapViewer

THUMB_WIDTH = 160


class LiveView:
    def __init__(self, host: str = "127.0.0.1", port: int = 8080, every_s: float = 3.0):
        if not every_s > 0:
            raise ValueError(f"every_s must be positive, got {every_s}")
        self.viewer = MapViewer(host, port, title="eligsir map (live)")
        self.every_s = float(every_s)
        self.pushes = 0
        self.push_s = 0.0  # seconds spent in pushes (inside the excluded callback time)
        self._last = -math.inf
        self._frame = None
        self._path: list[tuple[int, np.ndarray]] = []  # (frame index, T_world_cam as integrated)
        self._new_client = False
        self._started = False
        server = self.viewer.server
        with self.viewer._layers:
            self._follow = server.gui.add_checkbox("Follow the camera", initial_value=False)
        self._status = server.gui.add_markdown("waiting for the first frame")

        @server.on_client_connect
        def _(_client) -> None:
            self._new_client = True

    @property
    def url(self) -> str:
        return self.viewer.url

    def attach(self, rec) -> None:
        """Feed the page from ``rec``'s update loop (``rec.callbacks``, whose time is excluded from mapping)."""
        rec.callbacks.append(self.on_update)

    def observe(self, frame) -> None:
        """A frame was released to the mapper: it is the current camera."""
        self._frame = frame
        self._path.append((int(frame.index), np.asarray(frame.T_world_cam, dtype=np.float64).copy()))

    def on_update(self, rec) -> None:
        now = time.perf_counter()
        if not self._new_client and now - self._last < self.every_s:
            return
        if not self.viewer.server.get_clients():
            return
        self._new_client = False
        self._last = now
        self.push(rec)
        self.push_s += time.perf_counter() - now

    def push(self, rec) -> None:
        """Send the current splats, camera and path to every open page."""
        splats = splats_from_map(rec.gmap)
        if len(splats) == 0:
            return
        v = self.viewer
        v.set_splats(splats)
        f = self._frame
        if f is not None:
            T = np.asarray(f.T_world_cam, dtype=np.float64)
            if not self._started:  # pages opened from now on start behind the first camera
                v.set_start_view(splats, T, f.camera)
                self._started = True
            v.camera = f.camera
            scale = 0.05 * v.scene_size
            v._frustum("/live/camera", T, f.camera, (240, 60, 40), scale, image=_thumbnail(f.color))
            if len(self._path) > 1:
                c = self.path_centres(rec)
                v.server.scene.add_line_segments("/live/path", np.stack([c[:-1], c[1:]], 1), colors=(230, 120, 30),
                                                 thickness=2.0, thickness_units="screen")
            if self._follow.value:
                for client in v.server.get_clients().values():
                    v.go_to(client, T)
        self._status.content = (f"mapping: frame {getattr(f, 'index', '-')}, {len(splats)} Gaussians, "
                                f"{rec.stats.updates} updates")
        self.pushes += 1

    def path_centres(self, rec) -> np.ndarray:
        """[n, 3] camera centres of the frames so far, at their poses now: where loop closure (``rec.loops``)
        corrected them, the path jumps into place at the next push."""
        loops = getattr(rec, "loops", None)
        poses = [T if loops is None else loops.pose_of(i, T) for i, T in self._path]
        return np.stack([T[:3, 3] for T in poses])

    def show_results(self, out_dir: str | Path) -> None:
        """Replace the live scene with the saved map of a finished run (splats, cameras, go-to buttons)."""
        from ..export.views import DEFAULT_CAMERA, camera_next_to
        from ..pose.trajectory import read_tum_trajectory
        from .splats import read_splats

        out = Path(out_dir)
        v = self.viewer
        for name in ("/live/camera", "/live/path"):
            v.server.scene.remove_by_name(name)
        splats = read_splats(out / "map.ply")
        v.set_splats(splats)
        if (out / "trajectory.txt").is_file():
            _, poses = read_tum_trajectory(out / "trajectory.txt")
            v.set_trajectory(poses, camera_next_to(out / "map.ply") or DEFAULT_CAMERA)
        self._status.content = f"done: {len(splats)} Gaussians in {out / 'map.ply'}"

    def close(self) -> None:
        self.viewer.close()


def _thumbnail(color) -> np.ndarray:
    """[h, w, 3] uint8 of a frame's colour [H, W, 3] float, ``THUMB_WIDTH`` wide (the image on the frustum)."""
    import cv2

    img = (np.clip(color.detach().cpu().numpy() if hasattr(color, "detach") else np.asarray(color), 0, 1) * 255)
    img = img.astype(np.uint8)
    h, w = img.shape[:2]
    return cv2.resize(img, (THUMB_WIDTH, max(1, round(h * THUMB_WIDTH / w))), interpolation=cv2.INTER_AREA)
