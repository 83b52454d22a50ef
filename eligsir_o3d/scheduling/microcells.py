"""World-space microcells on an Open3D hash map: the spatial signal of Map-Guided View Scheduling.

The paper divides the observed scene into fixed world-space microcells and accumulates reconstruction error from
the training renders that optimisation already produces; views covering weak or regressed cells are replayed more
often. :class:`VoxelHash` (integer voxel key -> dense id, ``o3d.core.HashMap``) is shared with the evidence store of
Targeted Geometry Growth; per-cell statistics live in torch arrays indexed by that id, so a rehash of the Open3D
table (which reallocates its buffers) never moves them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d.core as o3c
import torch

from ..core.camera import Camera
from ..core.voxels import unique_keys
from .cell_feedback import FeedbackPlan, fold_torch, make_plan



def _to_o3d(t: torch.Tensor) -> o3c.Tensor:
    return o3c.Tensor.from_dlpack(torch.utils.dlpack.to_dlpack(t.contiguous()))


def _to_torch(t: o3c.Tensor) -> torch.Tensor:
    return torch.utils.dlpack.from_dlpack(t.to_dlpack())


def world_points(depth: torch.Tensor, camera: Camera, T_world_cam, max_samples: int):
    """World points [M, 3] of valid depth pixels on a regular grid of at most ~``max_samples`` pixels.

    depth [h, w] metres at ``camera``'s resolution. Returns (points [M, 3], flat pixel indices [M]).
    """
    h, w = depth.shape
    stride = max(1, int(np.ceil(np.sqrt(h * w / max(1, max_samples)))))
    pts, pix = camera.backproject(depth.cpu(), stride)
    T = torch.as_tensor(np.asarray(T_world_cam), dtype=torch.float32)
    return pts @ T[:3, :3].T + T[:3, 3], pix


class VoxelHash:
    """Integer voxel keys -> dense ids 0..n-1 on an ``o3d.core.HashMap`` (Int32 keys of shape 3, CPU).

    Duplicate keys are removed in torch before they reach Open3D (duplicates in one batch get garbage indices),
    and the value buffer is re-fetched after every insert (a rehash reallocates it).
    """

    def __init__(self, voxel_size: float, capacity: int = 4096):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self._table = o3c.HashMap(capacity, key_dtype=o3c.int32, key_element_shape=(3,), value_dtypes=[o3c.int32],
                                  value_element_shapes=[(1,)], device=o3c.Device("CPU:0"))
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def keys_of(self, points: torch.Tensor) -> torch.Tensor:  # [M, 3] metres -> [M, 3] int32
        return torch.floor(points.detach().cpu().float() / self.voxel_size).to(torch.int32)

    def lookup(self, points: torch.Tensor, insert: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Ids [M] int64 of the voxels containing ``points`` [M, 3] (-1 where absent and not inserted), and a bool
        [M] mask of points whose voxel was created by this call."""
        keys = self.keys_of(points)
        if keys.shape[0] == 0:
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.bool)
        ukeys, inverse = unique_keys(keys)
        ids, found = self._find(ukeys)
        new = ~found
        if insert and bool(new.any()):
            n_new = int(new.sum())
            values = torch.arange(self.size, self.size + n_new, dtype=torch.int32)[:, None]
            self._table.insert(_to_o3d(ukeys[new]), _to_o3d(values))
            ids[new] = values[:, 0].long()
            self.size += n_new
        return ids[inverse], new[inverse] if insert else torch.zeros_like(inverse, dtype=torch.bool)

    def _find(self, ukeys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        buf, mask = self._table.find(_to_o3d(ukeys))
        found = _to_torch(mask).clone()
        values = _to_torch(self._table.value_tensor())  # re-fetched: inserts may have reallocated it
        ids = torch.full((ukeys.shape[0],), -1, dtype=torch.long)
        if bool(found.any()):
            ids[found] = values[_to_torch(buf).long()[found], 0].long()
        return ids, found

    def keys(self) -> torch.Tensor:
        """[n, 3] int32 keys ordered by id."""
        buf = _to_torch(self._table.active_buf_indices()).long()
        keys = _to_torch(self._table.key_tensor())[buf].clone()
        ids = _to_torch(self._table.value_tensor())[buf, 0].long()
        out = torch.zeros(self.size, 3, dtype=torch.int32)
        out[ids] = keys
        return out

    def state_dict(self) -> dict:
        return {"voxel_size": self.voxel_size, "keys": self.keys()}

    def load_state_dict(self, state: dict) -> None:
        self.__init__(float(state["voxel_size"]), max(4096, 2 * len(state["keys"])))
        keys = state["keys"].to(torch.int32)
        if keys.shape[0]:
            self._table.insert(_to_o3d(keys), _to_o3d(torch.arange(keys.shape[0], dtype=torch.int32)[:, None]))
            self.size = keys.shape[0]


def grow(t: torch.Tensor, n: int, fill) -> torch.Tensor:
    """``t`` [m, ...] extended to at least n rows with ``fill`` (capacity doubles, amortised O(1))."""
    if t.shape[0] >= n:
        return t
    extra = torch.full((max(n, 2 * t.shape[0]) - t.shape[0], *t.shape[1:]), fill, dtype=t.dtype, device=t.device)
    return torch.cat([t, extra], 0)


@dataclass
class MicrocellConfig:
    cell_size: float = 0.25
    """Metres: edge of a microcell; a few cells per view at indoor depths (the evaluation's cells are coarser)."""
    ema: float = 0.3
    """Weight in [0, 1] of a new error observation in a cell's running error."""
    init_error: float = 0.15
    """Photometric L1 assumed for a cell that no training render has measured yet."""
    samples: int = 1024
    """Depth samples per view for its cell footprint and for splatting its error."""


class Microcells:
    """Fixed world-space cells accumulating the photometric error of training renders (paper: "spatial
    supervision focus"). Per cell: running error (EMA), the best running error so far (to detect regression),
    visits (training renders that measured it) and coverage (retained views that see it).

    The running error, best error and visits live on ``device`` (the map's: the training renders' errors are
    folded in there, :mod:`.cell_feedback`); the policy reads them through :meth:`host`. Coverage and the hash stay
    on the CPU."""

    def __init__(self, cfg: MicrocellConfig | None = None):
        self.cfg = cfg or MicrocellConfig()
        self.hash = VoxelHash(self.cfg.cell_size)
        self.device = torch.device("cpu")
        self.error = torch.zeros(0)
        self.best = torch.zeros(0)
        self.visits = torch.zeros(0, dtype=torch.long)
        self.coverage = torch.zeros(0, dtype=torch.long)
        self.folds = 0  # error maps folded in so far
        self._host: tuple[int, tuple] | None = None  # (folds, (error, best, visits)) copied at that count

    def __len__(self) -> int:
        return len(self.hash)

    def to(self, device) -> "Microcells":
        """Keep the running error, best error and visits on ``device``."""
        self.device = torch.device(device)
        self.error, self.best, self.visits = (t.to(self.device) for t in (self.error, self.best, self.visits))
        self._host = None
        return self

    def host(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(error, best, visits) on the CPU: the tensors themselves on a CPU map, else one copy per fold count."""
        if self.device.type == "cpu":
            return self.error, self.best, self.visits
        if self._host is None or self._host[0] != self.folds or self._host[1][0].shape[0] != self.error.shape[0]:
            self._host = (self.folds, tuple(t.cpu() for t in (self.error, self.best, self.visits)))
        return self._host[1]

    def _ensure(self) -> None:
        n = len(self.hash)
        self.error = grow(self.error, n, self.cfg.init_error)
        self.best = grow(self.best, n, float("inf"))
        self.visits = grow(self.visits, n, 0)
        self.coverage = grow(self.coverage, n, 0)

    def locate(self, depth: torch.Tensor, camera: Camera, T_world_cam, insert: bool = True):
        """(flat pixel indices [M], cell ids [M]) of a view's depth samples (-1 ids: cells not inserted)."""
        pts, pix = world_points(depth, camera, T_world_cam, self.cfg.samples)
        ids, _ = self.hash.lookup(pts, insert=insert)
        self._ensure()
        return pix, ids

    def footprint(self, depth: torch.Tensor, camera: Camera, T_world_cam) -> tuple[torch.Tensor, torch.Tensor]:
        """(cell ids [C], weights [C] summing to 1): the share of a view's depth samples in each cell."""
        _, ids = self.locate(depth, camera, T_world_cam)
        cells, counts = torch.unique(ids, return_counts=True)
        return cells, counts.float() / counts.sum().clamp_min(1)

    def add_coverage(self, cells: torch.Tensor, delta: int = 1) -> None:
        self.coverage[cells] += delta

    def plan(self, depth: torch.Tensor, camera: Camera, T_world_cam) -> FeedbackPlan:
        """The :class:`~.cell_feedback.FeedbackPlan` of a view's depth samples at ``camera``'s resolution."""
        pix, ids = self.locate(depth, camera, T_world_cam)
        return make_plan(pix, ids, camera.height * camera.width, self.device)

    def fold(self, plan: FeedbackPlan, error_map: torch.Tensor, fold_fn=None) -> None:
        """Fold a training render's error ``error_map`` [P] (flat) into the cells of ``plan``, by ``fold_fn``
        (a kernel set's fused fold) or :func:`~.cell_feedback.fold_torch`."""
        (fold_fn or fold_torch)(plan, error_map, self.error, self.best, self.visits, self.cfg.ema)
        self.folds += 1

    def need(self, cells: torch.Tensor, good_error: float, regress_gain: float, regress_margin: float) -> torch.Tensor:
        """How much supervision each cell still needs: error above ``good_error`` plus a bonus for regression
        (running error risen more than ``regress_margin`` above its best)."""
        error, best, _ = self.host()
        err = error[cells]
        regress = (err - best[cells] - regress_margin).clamp_min(0)
        regress = torch.where(torch.isfinite(regress), regress, torch.zeros_like(regress))
        return (err - good_error).clamp_min(0) + regress_gain * regress

    def state_dict(self) -> dict:
        n = len(self)
        error, best, visits = self.host()
        return {"hash": self.hash.state_dict(), "error": error[:n].clone(), "best": best[:n].clone(),
                "visits": visits[:n].clone(), "coverage": self.coverage[:n].clone()}

    def load_state_dict(self, state: dict) -> None:
        self.hash.load_state_dict(state["hash"])
        self.error, self.best = state["error"].to(self.device).clone(), state["best"].to(self.device).clone()
        self.visits, self.coverage = state["visits"].to(self.device).clone(), state["coverage"].clone()
        self._host = None
