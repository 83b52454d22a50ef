"""The checkpoint state of a :class:`.loop_closure.LoopClosure`: plain containers and arrays, and its restoring.

A settled keyframe keeps its cloud (points and normals); an unsettled one keeps the inputs of its build (strided
depth and intrinsics), so a resumed run builds it again and settles it at the same frame. A state written before
keyframes settled late has every keyframe settled; one written before refined edges has no ``odo_rel`` (then the
tracker's relative poses), and one written before skip edges has none.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import invert_pose
from .loops import Keyframe
from .pose_graph import Edge


def state_of(lc) -> dict:
    """``lc``'s state: keyframes (index, tracker pose, cloud points and normals, or the inputs of an unsettled
    one's build), corrected poses, edges, frames' offsets, counters."""
    keys = []
    for k, key in enumerate(lc.keys):
        cloud = key.cloud if k < lc.settled else None
        row = {"index": key.index, "raw_pose": key.raw_pose,
               "points": np.zeros((0, 3)) if cloud is None else np.asarray(cloud.points).copy(),
               "normals": np.zeros((0, 3)) if cloud is None else np.asarray(cloud.normals).copy()}
        if k >= lc.settled:
            depth, intr = lc.inputs[k]
            row.update(depth=np.asarray(depth).copy(), intrinsics=list(intr))
        keys.append(row)
    edges = [{"source": e.source, "target": e.target, "transform": e.transform, "information": e.information}
             for e in lc.loop_edges]
    running = [lc._job] if lc._job else []
    return {"keys": keys, "settled": lc.settled, "corrected": [T.copy() for T in lc.corrected],
            "odo_rel": list(lc.odo_rel), "odo_info": list(lc.odo_info), "loop_edges": edges,
            "skip_edges": [{"source": e.source, "target": e.target, "transform": e.transform,
                            "information": e.information} for e in lc.skip_edges],
            "skips_optimised": lc._skips_optimised,
            "pruned": sorted(lc.pruned), "pending": [list(p) for p in running + lc.pending],  # running first
            "counts": dict(lc.counts), "seconds": lc.seconds, "wait_seconds": lc.wait_seconds,
            "keyframe_seconds": lc.keyframe_seconds,
            "frames": {int(i): [k, rel.copy()] for i, (k, rel) in lc.frames.items()},
            "raw": {int(i): T.copy() for i, T in lc.raw.items()}, "log": list(lc.log)}


def load_state(lc, state: dict) -> None:
    """Restore :func:`state_of`'s output into ``lc`` (whose worker process is closed)."""
    import open3d as o3d

    lc.keys, lc.inputs = [], {}
    lc.settled = int(state.get("settled", len(state["keys"])))
    for k, row in enumerate(state["keys"]):
        cloud = None
        if k < lc.settled:
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(row["points"], dtype=np.float64)))
            cloud.normals = o3d.utility.Vector3dVector(np.asarray(row["normals"], dtype=np.float64))
        else:
            lc.inputs[k] = (np.asarray(row["depth"]), tuple(float(x) for x in row["intrinsics"]))
        lc.keys.append(Keyframe(int(row["index"]), np.asarray(row["raw_pose"], dtype=np.float64), cloud))
    lc.corrected = [np.asarray(T, dtype=np.float64) for T in state["corrected"]]
    lc.odo_info = [np.asarray(x, dtype=np.float64) for x in state["odo_info"]]
    raw = [key.raw_pose for key in lc.keys]  # a checkpoint without refined edges: the tracker's
    lc.odo_rel = [np.asarray(x, dtype=np.float64) for x in state.get("odo_rel", [])] or (
        [np.eye(4)] + [invert_pose(a) @ b for a, b in zip(raw, raw[1:])])
    lc.loop_edges = [Edge(int(e["source"]), int(e["target"]), np.asarray(e["transform"], dtype=np.float64),
                          np.asarray(e["information"], dtype=np.float64), True) for e in state["loop_edges"]]
    lc.skip_edges = [Edge(int(e["source"]), int(e["target"]), np.asarray(e["transform"], dtype=np.float64),
                          np.asarray(e["information"], dtype=np.float64), False) for e in state.get("skip_edges", [])]
    lc._skips_optimised = int(state.get("skips_optimised", len(lc.skip_edges)))
    lc.pruned = {tuple(p) for p in state["pruned"]}
    lc.pending = [(int(k), int(j)) for k, j in state.get("pending", [])]
    lc.counts.update(state["counts"])
    lc.seconds = float(state["seconds"])
    lc.wait_seconds = float(state.get("wait_seconds", 0.0))
    lc.keyframe_seconds = float(state.get("keyframe_seconds", 0.0))
    lc.frames = {int(i): (int(v[0]), np.asarray(v[1], dtype=np.float64)) for i, v in state["frames"].items()}
    lc.raw = {int(i): np.asarray(T, dtype=np.float64) for i, T in state["raw"].items()}
    lc.log = list(state.get("log", []))
