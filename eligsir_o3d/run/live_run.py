"""Live mapping: one frame-source seam shared by a RealSense camera and recordings replayed at their own pace.

A :class:`FrameSource` has a ``camera``, a ``depth_scale`` and ``read()`` (block until the next RGB-D frame,
``None`` at the end). :class:`RealSenseCamera` wraps Open3D's ``o3d.t.io.RealSenseSensor``; :class:`RSBagReplay`
wraps ``o3d.t.io.RSBagReader`` (the same Open3D RGB-D video API: metadata, then one aligned RGBD image per call);
:class:`SequenceReplay` replays any sequence ``open_sequence`` reads (ROS bags, .sens, folders). The replays
deliver frames at the recording's pace, as a camera would.

:func:`run_live` maps such a stream against the wall clock: a capture thread puts frames in a bounded queue that
drops its oldest frame when full (as the real-time replay clock does); the mapper takes the oldest waiting
frame, tracks it (RGB-D odometry by default; loop closure corrects the poses, verifying loops in a worker
process), integrates it and optimises until the next frame is due, and keeps
optimising while nothing waits. When the stream ends (or ``max_frames`` / ``seconds`` is reached) it drains for
a bounded time and writes ``map.ply``, ``trajectory.txt``, ``config.json`` and ``live.json`` to ``out``.

The RealSense camera path has NOT met a camera: it is written against Open3D's documented RealSenseSensor API and
exercised only through :class:`RSBagReplay`, which shares every line of :func:`run_live` with it.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from pathlib import Path

import numpy as np

from ..core.camera import Camera

log = logging.getLogger("eligsir_o3d")


class FrameSource(ABC):
    """A stream of RGB-D frames: ``camera``, ``depth_scale``, ``read() -> (rgbd, timestamp_s) | None``."""

    camera: Camera
    depth_scale: float = 1000.0
    name: str = "frames"

    def start(self) -> None:
        """Open the device or file (called once, before the first ``read``)."""

    @abstractmethod
    def read(self):
        """Block until the next frame: ``(o3d.t.geometry.RGBDImage, timestamp in seconds)``, or None at the end."""

    def stop(self) -> None:
        """Release the device or file."""


def _camera_from_metadata(md) -> Camera:
    K = md.intrinsics.intrinsic_matrix
    return Camera(int(md.width), int(md.height), float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2]))


class RealSenseCamera(FrameSource):
    """A connected RealSense through ``o3d.t.io.RealSenseSensor`` (depth aligned to colour). Untested on hardware."""

    name = "realsense"

    def __init__(self, config: dict | None = None, device_index: int = 0) -> None:
        import open3d as o3d

        self._o3d = o3d
        self._config, self._index = config or {}, device_index
        self.sensor = None

    def start(self) -> None:
        o3d = self._o3d
        self.sensor = o3d.t.io.RealSenseSensor()
        cfg = o3d.t.io.RealSenseSensorConfig({k: str(v) for k, v in self._config.items()})
        if not self.sensor.init_sensor(cfg, self._index, ""):
            raise RuntimeError(f"no RealSense camera at index {self._index} (is one connected? "
                               f"o3d.t.io.RealSenseSensor.list_devices() lists them)")
        md = self.sensor.get_metadata()
        self.camera, self.depth_scale = _camera_from_metadata(md), float(md.depth_scale)
        self.sensor.start_capture(False)

    def read(self):
        rgbd = self.sensor.capture_frame(True, True)  # wait for a frame, align depth to colour
        return rgbd, self.sensor.get_timestamp() * 1e-6

    def stop(self) -> None:
        if self.sensor is not None:
            self.sensor.stop_capture()


class RSBagReplay(FrameSource):
    """A RealSense .bag through ``o3d.t.io.RSBagReader``, delivered at the recording's frame rate."""

    name = "realsense-bag"

    def __init__(self, path: str | Path, paced: bool = True) -> None:
        import open3d as o3d

        self.path, self.paced = Path(path), paced
        self.reader = o3d.t.io.RSBagReader()
        self._k, self._t0 = 0, 0.0

    def start(self) -> None:
        if not self.path.is_file() or not self.reader.open(str(self.path)):
            raise RuntimeError(f"{self.path}: Open3D's RSBagReader cannot open it (not a RealSense bag?)")
        md = self.reader.metadata
        self.camera, self.depth_scale, self.fps = _camera_from_metadata(md), float(md.depth_scale), float(md.fps)
        self._t0 = time.perf_counter()

    def read(self):
        while not self.reader.is_eof():
            rgbd = self.reader.next_frame()
            if rgbd.is_empty():
                continue
            ts = self._k / self.fps  # the reader's get_timestamp() does not follow the returned frame
            self._k += 1
            if self.paced:
                time.sleep(max(0.0, self._t0 + ts - time.perf_counter()))
            return rgbd, ts
        return None

    def stop(self) -> None:
        self.reader.close()


class SequenceReplay(FrameSource):
    """Any sequence from ``open_sequence`` (ROS bags, .sens, folders), delivered at its timestamps' pace."""

    name = "sequence"

    def __init__(self, seq, paced: bool = True, max_frames: int | None = None) -> None:
        self.seq, self.paced = seq, paced
        self.camera, self.depth_scale = seq.camera, seq.depth_scale
        self._n = len(seq) if max_frames is None else min(len(seq), max_frames)
        self._k = 0

    def start(self) -> None:
        self._t0 = time.perf_counter()

    def read(self):
        if self._k >= self._n:
            return None
        item = self.seq[self._k]
        ts = float(item.timestamp - self.seq.timestamps[0])
        self._k += 1
        if self.paced:
            time.sleep(max(0.0, self._t0 + ts - time.perf_counter()))
        return item.rgbd, ts


def _capture(source: FrameSource, queue: deque, lock: threading.Lock, stats: dict, done: threading.Event,
             queue_size: int, max_frames: int | None, seconds: float | None) -> None:
    """The capture thread: read frames into ``queue`` (the oldest waiting one dropped beyond ``queue_size``) until
    the source ends, ``max_frames`` are captured or ``seconds`` have passed; then set ``done``."""
    t_end = None if seconds is None else time.perf_counter() + seconds
    try:
        while not done.is_set():
            item = source.read()
            if item is None or (t_end is not None and time.perf_counter() > t_end):
                break
            with lock:
                if len(queue) >= queue_size:
                    queue.popleft()
                    stats["dropped"] += 1
                queue.append((stats["captured"], *item))
                stats["captured"] += 1
            if max_frames is not None and stats["captured"] >= max_frames:
                break
    finally:
        done.set()


def _write_outputs(out: Path, rec, config, source: FrameSource, tracker, stats: dict, stamps: list, poses: list,
                   wall0: float) -> dict:
    """map.ply, trajectory.txt, config.json (``config`` as given) and live.json (the summary, returned)."""
    from ..io.atomic import atomic_write_text
    from ..pose import write_tum_trajectory

    rec.save_ply(out / "map.ply")
    if stamps:
        write_tum_trajectory(out / "trajectory.txt", stamps, poses)
    atomic_write_text(out / "config.json", json.dumps(config.to_dict(), indent=2))
    summary = {"source": source.name, **stats, "gaussians": len(rec.gmap), "updates": rec.stats.updates,
               "wall_s": time.perf_counter() - wall0, "tracking_ms_per_frame": tracker.ms_per_frame,
               "loop_closure": None if rec.loops is None else rec.loops.counters(),
               "camera": {"width": source.camera.width, "height": source.camera.height, "fx": source.camera.fx,
                          "fy": source.camera.fy, "cx": source.camera.cx, "cy": source.camera.cy}}
    atomic_write_text(out / "live.json", json.dumps(summary, indent=1))
    return summary


def run_live(source: FrameSource, out: str | Path, config=None, *, pose: str = "odometry", max_frames: int | None = None,
             seconds: float | None = None, queue_size: int = 4, drain_s: float = 2.0) -> dict:
    """Map ``source`` in real time into ``out`` (see the module docstring). Returns the summary in live.json.
    The folder is held with the run lock (:mod:`.lock`: one run per folder, never written through a link) for the
    whole run, and every file is written atomically."""
    from .lock import RunLock

    out = Path(out)
    with RunLock(out):
        return _run_live(source, out, config, pose=pose, max_frames=max_frames, seconds=seconds,
                         queue_size=queue_size, drain_s=drain_s)


def _run_live(source: FrameSource, out: Path, config, *, pose: str, max_frames: int | None, seconds: float | None,
              queue_size: int, drain_s: float) -> dict:
    from ..config import Config
    from ..core.frame import Frame, FrameError
    from ..pose import TrackingLost, get_pose_source
    from ..mapper import Reconstructor

    config = config or Config()
    source.start()
    config.depth_scale = float(source.depth_scale)
    if str(config.loops.background).lower() == "auto":  # a live stream never waits for a loop's registration
        config.loops.background = "on"
    tracker = get_pose_source(pose)
    tracker.prepare(None)
    rec = Reconstructor(source.camera, config.device, config, pose_source=tracker)  # tracks, and closes loops
    rec.warmup()
    queue: deque = deque()
    stats = {"captured": 0, "dropped": 0, "integrated": 0, "lost": 0, "bad": 0}
    done = threading.Event()
    lock = threading.Lock()

    thread = threading.Thread(target=_capture, args=(source, queue, lock, stats, done, queue_size, max_frames, seconds),
                              name="eligsir-capture", daemon=True)
    wall0 = time.perf_counter()
    thread.start()
    stamps, poses, period = [], [], 1.0 / 30.0
    try:
        while not (done.is_set() and not queue):
            with lock:
                item = queue.popleft() if queue else None
                rec.backlog = len(queue)
            if item is None:
                if len(rec.gmap) and rec.optimize(deadline=rec.clock_now() + 0.01) == 0:
                    time.sleep(0.002)
                elif not len(rec.gmap):
                    time.sleep(0.002)
                continue
            index, rgbd, ts = item
            if stamps and ts > stamps[-1]:
                period = (ts - stamps[0]) / max(1, len(stamps))
            attach = getattr(rec.fidelity, "attach", None)
            if attach is not None:
                attach(period, None)
            try:
                frame = Frame.from_rgbd(rgbd, source.camera, np.eye(4), depth_scale=config.depth_scale,
                                        depth_max=config.depth_max, timestamp=ts, index=index)
                frame.T_world_cam = rec.track(frame)  # the tracker's pose, corrected by loop closure
                if queue:  # behind: one update, then the next frame (as the real-time replay clock does)
                    rec.integrate(frame, updates=1)
                else:
                    rec.integrate(frame, deadline=rec.clock_now() + period)
            except TrackingLost as e:
                stats["lost"] += 1
                log.warning("%s", e)
                continue
            except FrameError as e:
                stats["bad"] += 1
                log.warning("skipping %s", e)
                continue
            stats["integrated"] += 1
            stamps.append(ts)
            poses.append((frame.index, frame.T_world_cam))
    finally:
        done.set()
        thread.join(timeout=5.0)
        source.stop()
    rec.finalize(rec.clock_now() + drain_s)
    poses = [T if rec.loops is None else rec.loops.pose_of(i, T) for i, T in poses]  # the final loop-closed poses
    return _write_outputs(out, rec, config, source, tracker, stats, stamps, poses, wall0)
