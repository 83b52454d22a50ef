"""The replay benchmark's edge report (benchmarks/quality/loops.py): graph edges against the ground truth."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

loops_bench = pytest.importorskip("benchmarks.quality.loops")

from eligsir_o3d.core.camera import invert_pose  # noqa: E402
from eligsir_o3d.pose.loops import Keyframe  # noqa: E402
from eligsir_o3d.pose.pose_graph import Edge  # noqa: E402


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
    T[0, 3] = x
    return T


def _shift(T: np.ndarray, dx: float) -> np.ndarray:
    D = np.eye(4)
    D[1, 3] = dx
    return T @ D


def test_edge_report_measures_each_kind_against_ground_truth():
    gt = {i: _pose(0.1 * i, 2.0 * i) for i in range(0, 50, 10)}  # frames 0, 10, 20, 30, 40
    keys = [Keyframe(i, gt[i], None) for i in sorted(gt)]
    rel = [np.eye(4)] + [invert_pose(gt[a]) @ gt[b] for a, b in zip(sorted(gt), sorted(gt)[1:])]
    rel[2] = _shift(rel[2], 0.01)  # edge 10 -> 20 is 1 cm off
    info = [np.eye(6) * 100.0 for _ in rel]
    # two loops onto keyframe 0 from keyframes 3 and 4, both 3 cm off the same way in keyframe 0's axes
    offset = np.eye(4)
    offset[1, 3] = 0.03
    loops = [Edge(k, 0, offset @ invert_pose(gt[0]) @ gt[keys[k].index], np.eye(6) * 200.0, True) for k in (3, 4)]
    loops.append(Edge(2, 0, offset @ invert_pose(gt[0]) @ gt[20], np.eye(6), True))  # shares source 2 with ...
    loops.append(Edge(2, 1, offset @ invert_pose(gt[10]) @ gt[20], np.eye(6), True))  # ... this one (pair 2)
    loops.append(Edge(4, 1, _shift(invert_pose(gt[10]) @ gt[40], 0.05), np.eye(6), True))  # pruned: no pair
    lc = SimpleNamespace(keys=keys, settled=len(keys), odo_rel=rel, odo_info=info, loop_edges=loops,
                         pruned={(4, 1)})
    rows = loops_bench.graph_edges(lc, gt)
    assert [r["kind"] for r in rows] == ["odometry"] * 4 + ["loop"] * 4 + ["pruned"]
    assert rows[1]["cm"] == pytest.approx(1.0) and rows[0]["cm"] == pytest.approx(0.0, abs=1e-9)
    assert rows[4]["cm"] > 2.0 and rows[8]["cm"] == pytest.approx(5.0)
    assert rows[1]["chi2"] == pytest.approx(100.0 * 0.01 ** 2) and rows[4]["count"] == 200.0
    # loops onto keyframe 0 share their offset there: the poses they imply between their sources (3-4, 3-2, 4-2)
    # are exact; 2->0 and 2->1 carry the offset in two targets' axes, 20 degrees apart: their pair is not
    pairs = sorted(p[0] for p in loops_bench.loop_pair_errors(lc, gt))
    assert len(pairs) == 4 and max(pairs[:3]) == pytest.approx(0.0, abs=1e-6) and pairs[3] > 0.5
    s = loops_bench.edge_summary(lc, gt)
    assert s["odometry"]["edges"] == 4 and s["loop"]["edges"] == 4 and s["pruned"]["edges"] == 1
    assert s["loop_pairs"]["pairs"] == 4
