"""An Open3D pose graph over keyframes: tracker (odometry) edges between consecutive keyframes, loop edges from
verified registrations, optimised with ``global_optimization`` (Levenberg-Marquardt with the line process that
down-weights and prunes loop edges the rest of the graph disagrees with).

Conventions (Open3D's): a node's pose is ``T_world_cam``; an edge ``(s, t, T)`` says ``T = inv(pose_t) @ pose_s``
(it maps source camera points into the target camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


REG = o3d.pipelines.registration


@dataclass
class GraphConfig:
    """Pose-graph optimisation settings (Open3D's ``GlobalOptimizationOption``)."""

    max_correspondence_distance: float = 0.03
    """The line process's residual scale (m)."""
    edge_prune_threshold: float = 0.25
    """Loop edges whose line-process weight falls below this are pruned."""
    preference_loop_closure: float = 1.0
    """Weight of loop edges against odometry edges."""
    odometry_weight: float = 1.0
    """Scales the tracker edges' information matrices."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations."""


@dataclass
class Edge:
    """A graph edge between keyframe positions ``source`` and ``target``."""

    source: int
    target: int
    transform: np.ndarray  # inv(pose_target) @ pose_source
    information: np.ndarray  # [6, 6]
    loop: bool


def optimise(poses: list[np.ndarray], edges: list[Edge], cfg: GraphConfig) -> tuple[list[np.ndarray], list[bool]]:
    """Optimised node poses (node 0 held fixed) and, per loop edge in order, whether it survived the pruning."""
    graph = REG.PoseGraph()
    for T in poses:
        graph.nodes.append(REG.PoseGraphNode(np.asarray(T, dtype=np.float64)))
    loops = []
    for e in edges:
        info = e.information if e.loop else e.information * cfg.odometry_weight
        graph.edges.append(REG.PoseGraphEdge(e.source, e.target, e.transform, info, uncertain=e.loop))
        if e.loop:
            loops.append((e.source, e.target))
    option = REG.GlobalOptimizationOption(max_correspondence_distance=cfg.max_correspondence_distance,
                                          edge_prune_threshold=cfg.edge_prune_threshold,
                                          preference_loop_closure=cfg.preference_loop_closure, reference_node=0)
    criteria = REG.GlobalOptimizationConvergenceCriteria()
    criteria.max_iteration = int(cfg.max_iterations)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        REG.global_optimization(graph, REG.GlobalOptimizationLevenbergMarquardt(), criteria, option)
    kept = {(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain}
    out = [np.asarray(n.pose).copy() for n in graph.nodes]
    return out, [pair in kept for pair in loops]


def odometry_edges(relative: list[np.ndarray], information: list[np.ndarray]) -> list[Edge]:
    """Odometry edges between consecutive keyframes: ``relative[k]`` (``T_prev_k``) and ``information[k]`` are
    those of the edge ``k - 1 -> k`` (index 0 is unused)."""
    return [Edge(k, k - 1, relative[k], information[k], False) for k in range(1, len(relative))]
