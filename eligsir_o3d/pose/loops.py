"""Loop detection between keyframes of a tracked run: candidates near in space, verified by registration.

A keyframe keeps a small point cloud of its depth (camera axes, voxel-downsampled, with normals). A loop
candidate for a new keyframe is an earlier keyframe far back in time (``min_gap`` frames) whose camera, at the
current corrected estimate, is near (``radius`` m) and looks the same way (``max_angle_deg``). A candidate is
verified by registering two small local maps (each keyframe fused with its ``local`` predecessors) with
multi-scale generalized ICP started at the current estimate (the pose prior), then tested: the fitness (the
share of points with a neighbour within ``max_dist``), the inlier RMSE, and how far the correction moves away
from the estimate (a loop edge that wants to move the camera by more than the drift can have built is wrong).
"""

from __future__ import annotations

import dataclasses
import time

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from ..core.camera import Camera, invert_pose, rotation_angle_deg


@dataclass
class LoopConfig:
    """Loop detection and verification settings (metres, degrees, frames)."""

    keyframe_dist: float = 0.1
    """A frame becomes a keyframe once it moved this far from the last one (m)."""
    keyframe_angle_deg: float = 10.0
    """A frame becomes a keyframe once it turned this far from the last one (deg)."""
    keyframe_every: int = 30
    """A frame becomes a keyframe once this many frames passed since the last one."""
    cloud_voxel: float = 0.02
    """Voxel size of a keyframe's point cloud (m)."""
    cloud_stride: int = 4
    """Pixel stride of the depth samples a keyframe's cloud starts from."""
    depth_max: float = 4.0
    """Depth used for keyframe clouds (m)."""
    local: int = 2
    """Predecessors fused into a keyframe's local map for verification."""
    min_gap: int = 150
    """Frames between a keyframe and a loop candidate, at least."""
    radius: float = 0.6
    """Camera centres of a candidate pair this close at the current estimate (m)."""
    max_angle_deg: float = 35.0
    """Viewing directions of a candidate pair this close at the current estimate (deg)."""
    max_candidates: int = 2
    """Candidates verified per keyframe (nearest first)."""
    per_frame: int = 1
    """Candidates verified per frame at most (the rest wait for the next frames: a bounded slice of work)."""
    settle_frames: int = 3
    """A keyframe's cloud and odometry edge enter the graph this many frames after it (real-time clock: once built)."""
    icp_coarse: float = 0.08
    """The first ICP round's correspondence distance (m); then half of it, then ``max_dist``."""
    max_dist: float = 0.02
    """The fitness and RMSE test's correspondence distance (m)."""
    min_fitness: float = 0.6
    """Share of the source's points within max_dist after registration, at least."""
    refine_edges: str = "auto"
    """Odometry edges registered keyframe to keyframe where that fits better: auto (``refine_sources``), on, off."""
    refine_sources: str = "kiss-icp"
    """Pose sources (comma-separated names) whose edges ``refine_edges = auto`` refines (depth-only trackers)."""
    refine_min_gain: float = 0.0
    """A refined edge replaces the tracker's only where its fitness (at ``max_dist``) is this much higher."""
    refine_max_shift: float = 0.3
    """A refined edge moves the tracker's relative pose by at most this (m; the loop test's ``max_shift``)."""
    refine_max_turn_deg: float = 10.0
    """A refined edge turns the tracker's relative pose by at most this (deg; the loop test's ``max_turn_deg``)."""
    skip_edges: str = "auto"
    """Keyframes also registered two back, a second graph edge per keyframe: auto (``refine_sources``), on, off."""
    max_rmse: float = 0.013
    """Inlier RMSE after registration (m)."""
    max_shift: float = 0.3
    """The loop edge moves the estimate by at most this (m)."""
    max_turn_deg: float = 10.0
    """The loop edge turns the estimate by at most this (deg)."""
    min_points: int = 500
    """A keyframe cloud with fewer points takes part in no loop."""


def for_source(cfg: LoopConfig, source: str) -> LoopConfig:
    """``cfg`` for the pose source named ``source``: ``refine_edges = auto`` and ``skip_edges = auto`` resolved
    to on (one of the ``refine_sources``) or off."""
    listed = bool(source) and source in [s.strip() for s in cfg.refine_sources.split(",")]
    resolved = {}
    for name in ("refine_edges", "skip_edges"):
        mode = str(getattr(cfg, name)).lower()
        if mode not in ("auto", "on", "off"):
            raise ValueError(f"loops.detect.{name} must be auto, on or off, got {getattr(cfg, name)!r}")
        resolved[name] = ("on" if listed else "off") if mode == "auto" else mode
    return dataclasses.replace(cfg, **resolved)


@dataclass
class Keyframe:
    """One node of the pose graph: the frame index, its tracker pose, its cloud (camera axes; None until
    :func:`keyframe_data` built it)."""

    index: int
    raw_pose: np.ndarray  # T_world_cam as the tracker gave it
    cloud: o3d.geometry.PointCloud | None
    local_cloud: o3d.geometry.PointCloud | None = field(default=None, repr=False)


@dataclass
class LoopResult:
    """A verified (or failed) registration of keyframe ``source`` onto keyframe ``target``."""

    source: int  # keyframe ids (positions in the keyframe list)
    target: int
    transform: np.ndarray  # T_target_source: source camera points into the target camera
    fitness: float
    rmse: float
    shift: float  # how far the result moves the source from the prior estimate (m, deg)
    turn_deg: float
    accepted: bool
    information: np.ndarray | None = None


def keyframe_cloud(depth: np.ndarray, camera: Camera, cfg: LoopConfig) -> o3d.geometry.PointCloud:
    """A keyframe's point cloud from its depth [H, W] (metres, 0 = none), camera axes, with normals."""
    return cloud_from_depth(strided_depth(depth, cfg), intrinsics(camera), cfg)


def strided_depth(depth, cfg: LoopConfig) -> np.ndarray:
    """The depth samples a keyframe's cloud starts from: every ``cloud_stride``-th pixel of ``depth`` [H, W] (a
    numpy array or a torch tensor on any device; only the samples are copied), in its own dtype."""
    s = cfg.cloud_stride
    d = depth[::s, ::s]
    if hasattr(d, "detach"):
        d = d.detach().cpu().numpy()
    return np.ascontiguousarray(d)


def intrinsics(camera: Camera) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of ``camera``."""
    return float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)


def cloud_from_depth(strided: np.ndarray, intr: tuple, cfg: LoopConfig) -> o3d.geometry.PointCloud:
    """A keyframe's cloud from :func:`strided_depth`'s samples and :func:`intrinsics`' ``(fx, fy, cx, cy)``:
    back-projected (depth within 0.1 m and ``depth_max``), voxel-downsampled, with normals."""
    s, (fx, fy, cx, cy) = cfg.cloud_stride, intr
    d = np.asarray(strided, dtype=np.float64)
    v, u = np.nonzero((d > 0.1) & (d < cfg.depth_max))
    z = d[v, u]
    x = (u * s - cx) * z / fx
    y = (v * s - cy) * z / fy
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.stack([x, y, z], 1)))
    pcd = pcd.voxel_down_sample(cfg.cloud_voxel)
    with_normals(pcd, cfg.cloud_voxel)
    return pcd


def with_normals(pcd: o3d.geometry.PointCloud, voxel: float) -> o3d.geometry.PointCloud:
    """Estimate normals (oriented toward the camera at the origin) in place; returns ``pcd``."""
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4.0 * voxel, max_nn=30))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    return pcd


def local_map(keys: list[Keyframe], k: int, cfg: LoopConfig) -> o3d.geometry.PointCloud:
    """Keyframe ``k``'s cloud fused with its ``cfg.local`` predecessors', in keyframe ``k``'s camera axes (the
    tracker's relative poses place them; drift over a few keyframes is small). Cached on the keyframe."""
    key = keys[k]
    if key.local_cloud is not None:
        return key.local_cloud
    fused = o3d.geometry.PointCloud(key.cloud)
    inv_k = invert_pose(key.raw_pose)
    for j in range(max(0, k - cfg.local), k):
        fused += o3d.geometry.PointCloud(keys[j].cloud).transform(inv_k @ keys[j].raw_pose)
    fused = fused.voxel_down_sample(cfg.cloud_voxel)
    if not fused.has_normals() or len(fused.normals) != len(fused.points):
        with_normals(fused, cfg.cloud_voxel)
    key.local_cloud = fused
    return fused


def candidates(k: int, indices: list[int], poses: list[np.ndarray], cfg: LoopConfig) -> list[int]:
    """Keyframes that may close a loop with keyframe ``k``: at least ``min_gap`` frames earlier, camera within
    ``radius`` and viewing direction within ``max_angle_deg`` at the current estimates ``poses``; nearest first."""
    T = poses[k]
    found = []
    for j in range(k):
        if indices[k] - indices[j] < cfg.min_gap:
            break
        d = float(np.linalg.norm(poses[j][:3, 3] - T[:3, 3]))
        c = float(np.clip(poses[j][:3, 2] @ T[:3, 2], -1.0, 1.0))
        if d <= cfg.radius and np.degrees(np.arccos(c)) <= cfg.max_angle_deg:
            found.append((d, j))
    return [j for _, j in sorted(found)[: cfg.max_candidates]]


def verify(keys: list[Keyframe], poses: list[np.ndarray], k: int, j: int, cfg: LoopConfig) -> LoopResult:
    """Register keyframe ``k``'s local map onto keyframe ``j``'s, from the estimate ``inv(poses[j]) @ poses[k]``,
    and test it (fitness, inlier RMSE, shift from the estimate). The accepted result carries the edge's
    information matrix."""
    src, tgt = local_map(keys, k, cfg), local_map(keys, j, cfg)
    prior = invert_pose(poses[j]) @ poses[k]
    if min(len(src.points), len(tgt.points)) < cfg.min_points:
        return LoopResult(k, j, prior, 0.0, float("inf"), 0.0, 0.0, False)
    T = register(src, tgt, prior, cfg)
    ev = o3d.pipelines.registration.evaluate_registration(src, tgt, cfg.max_dist, T)
    delta = invert_pose(prior) @ T
    shift, turn = float(np.linalg.norm(delta[:3, 3])), rotation_angle_deg(delta[:3, :3])
    ok = (ev.fitness >= cfg.min_fitness and ev.inlier_rmse <= cfg.max_rmse and shift <= cfg.max_shift
          and turn <= cfg.max_turn_deg)
    info = None
    if ok:
        info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(src, tgt, cfg.max_dist, T)
    return LoopResult(k, j, np.asarray(T), float(ev.fitness), float(ev.inlier_rmse), shift, turn, bool(ok), info)


def register(src, tgt, T: np.ndarray, cfg: LoopConfig) -> np.ndarray:
    """Multi-scale generalized ICP (plane to plane: it does not slide along flat surfaces as point-to-plane
    does) of ``src`` onto ``tgt`` from ``T``, at correspondence distances ``icp_coarse``, half of it, then
    ``max_dist``: small_gicp's, on one thread (deterministic), each cloud's covariances and the target's k-d tree
    computed once for the three scales."""
    import small_gicp

    source, target = _gicp_cloud(src), _gicp_cloud(tgt)
    tree = small_gicp.KdTree(target, num_threads=1)
    small_gicp.estimate_covariances(target, tree, num_neighbors=_GICP_NEIGHBOURS, num_threads=1)
    small_gicp.estimate_covariances(source, num_neighbors=_GICP_NEIGHBOURS, num_threads=1)
    T = np.asarray(T, dtype=np.float64)
    for dist in (cfg.icp_coarse, cfg.icp_coarse / 2.0, cfg.max_dist):
        T = small_gicp.align(target, source, tree, T, registration_type="GICP", max_correspondence_distance=dist,
                             num_threads=1, max_iterations=_GICP_ITERATIONS).T_target_source
    return np.asarray(T)


_GICP_NEIGHBOURS = 20  # the neighbourhood of a point's covariance (Open3D's GICP uses the same)
_GICP_ITERATIONS = 30


def _gicp_cloud(cloud: o3d.geometry.PointCloud):
    import small_gicp

    return small_gicp.PointCloud(np.asarray(cloud.points, dtype=np.float64))


def timed_verify(keys, poses, k: int, j: int, cfg: LoopConfig) -> tuple[LoopResult, float]:
    """:func:`verify`, and the seconds it took."""
    t0 = time.perf_counter()
    return verify(keys, poses, k, j, cfg), time.perf_counter() - t0


def _within_refinement(prior: np.ndarray, T: np.ndarray, cfg: LoopConfig) -> bool:
    """Whether registration ``T`` stays within ``refine_max_shift`` / ``refine_max_turn_deg`` of the tracker's
    relative pose ``prior``."""
    delta = invert_pose(prior) @ T
    return bool(np.linalg.norm(delta[:3, 3]) <= cfg.refine_max_shift
                and rotation_angle_deg(delta[:3, :3]) <= cfg.refine_max_turn_deg)


def odometry_edge(keys: list[Keyframe], k: int, cfg: LoopConfig, refine: bool) -> tuple[np.ndarray, np.ndarray, bool]:
    """The graph's edge from keyframe ``k - 1`` to ``k``: ``(T_prev_k, information, refined)``. The tracker's
    relative pose, or with ``refine`` keyframe ``k``'s cloud registered onto ``k - 1``'s from it, kept where its
    fitness gains ``refine_min_gain`` and it stays within ``refine_max_shift`` / ``refine_max_turn_deg`` of the
    tracker's: the loop test's bound, which drops only registrations gone astray, since the tracker's worst edges
    (a jump) are the ones a refinement is for. The information matrix is the clouds' overlap at the edge."""
    src, tgt = keys[k].cloud, keys[k - 1].cloud
    T = prior = invert_pose(keys[k - 1].raw_pose) @ keys[k].raw_pose
    refined = False
    if refine and min(len(src.points), len(tgt.points)) >= cfg.min_points:
        evaluate = o3d.pipelines.registration.evaluate_registration
        before = evaluate(src, tgt, cfg.max_dist, prior).fitness
        R = register(src, tgt, prior, cfg)
        if evaluate(src, tgt, cfg.max_dist, R).fitness >= before + cfg.refine_min_gain and _within_refinement(
                prior, R, cfg):
            T, refined = R, True
    info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(src, tgt, cfg.max_dist, T)
    return T, info, refined


def skip_edge(keys: list[Keyframe], k: int, cfg: LoopConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """The graph's second edge into keyframe ``k``, from keyframe ``k - 2``: ``(T_k2_k, information)``, keyframe
    ``k``'s cloud registered onto ``k - 2``'s from the tracker's relative pose, or None where a cloud is too small
    or the registration leaves the refinement's bound (``refine_max_shift`` / ``refine_max_turn_deg``). With the
    edge from ``k - 1`` it closes a triangle: a jump of the tracker (or a refinement that slid) in either edge is
    outvoted in the graph by the two registrations that span it."""
    src, tgt = keys[k].cloud, keys[k - 2].cloud
    if min(len(src.points), len(tgt.points)) < cfg.min_points:
        return None
    prior = invert_pose(keys[k - 2].raw_pose) @ keys[k].raw_pose
    T = register(src, tgt, prior, cfg)
    if not _within_refinement(prior, T, cfg):
        return None
    return T, o3d.pipelines.registration.get_information_matrix_from_point_clouds(src, tgt, cfg.max_dist, T)


@dataclass
class KeyframeData:
    """What a keyframe's depth gives the pose graph: its cloud (points and normals, camera axes), its odometry
    edge from the previous keyframe (``T_prev_k``, information, whether registration refined it) and, with
    ``skip_edges``, its :func:`skip_edge` from the keyframe before (``(T_k2_k, information)`` or None)."""

    points: np.ndarray
    normals: np.ndarray
    rel: np.ndarray
    info: np.ndarray
    refined: bool
    seconds: float = 0.0  # the time it took to build
    skip: tuple | None = None

    def cloud(self) -> o3d.geometry.PointCloud:
        """The cloud as an Open3D point cloud."""
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(self.points, dtype=np.float64)))
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(self.normals, dtype=np.float64))
        return pcd


def keyframe_data(keys: list[Keyframe], k: int, strided: np.ndarray, intr: tuple, cfg: LoopConfig) -> KeyframeData:
    """Build keyframe ``k``'s cloud from :func:`strided_depth`'s samples (``keys[k].cloud`` is set) and its
    :func:`odometry_edge` from keyframe ``k - 1`` (whose cloud must be set; refined where ``cfg.refine_edges`` is
    on) and, where ``cfg.skip_edges`` is on, its :func:`skip_edge` from ``k - 2``; keyframe 0's edge is the
    identity."""
    t0 = time.perf_counter()
    keys[k].cloud = cloud_from_depth(strided, intr, cfg)
    if k == 0:
        rel, info, refined = np.eye(4), np.eye(6), False
    else:
        rel, info, refined = odometry_edge(keys, k, cfg, str(cfg.refine_edges).lower() == "on")
    skip = skip_edge(keys, k, cfg) if k >= 2 and str(cfg.skip_edges).lower() == "on" else None
    cloud = keys[k].cloud
    return KeyframeData(np.asarray(cloud.points).copy(), np.asarray(cloud.normals).copy(), np.asarray(rel),
                        np.asarray(info), bool(refined), time.perf_counter() - t0,
                        None if skip is None else (np.asarray(skip[0]), np.asarray(skip[1])))
