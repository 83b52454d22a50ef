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
    extra = torch.full((max(n, 2 * t.shape[0]) - t.shape[0], *t.shape[1:]), fill, dtype=t.dtype)
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
    visits (training renders that measured it) and coverage (retained views that see it)."""

    def __init__(self, cfg: MicrocellConfig | None = None):
        self.cfg = cfg or MicrocellConfig()
        self.hash = VoxelHash(self.cfg.cell_size)
        self.error = torch.zeros(0)
        self.best = torch.zeros(0)
        self.visits = torch.zeros(0, dtype=torch.long)
        self.coverage = torch.zeros(0, dtype=torch.long)
        self._plans: dict = {}  # id(ids) -> (ids, their samples' pixels, slots, cells and counts)
        self._stats = None  # (error, best, visits) and their numpy views, while those tensors stay

    def __len__(self) -> int:
        return len(self.hash)

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

    def accumulate(self, ids: torch.Tensor, errors: torch.Tensor) -> torch.Tensor:
        """Fold per-sample errors [M] into their cells' running error; returns the cells touched."""
        keep = ids >= 0
        ids, errors = ids[keep], errors.detach().cpu().float()[keep]
        if ids.numel() == 0:
            return ids
        cells, inv = torch.unique(ids, return_inverse=True)
        sums = torch.zeros(cells.numel()).index_add_(0, inv, errors)
        counts = torch.zeros(cells.numel()).index_add_(0, inv, torch.ones_like(errors))
        obs = sums / counts
        fresh = self.visits[cells] == 0
        a = self.cfg.ema
        self.error[cells] = torch.where(fresh, obs, (1 - a) * self.error[cells] + a * obs)
        self.visits[cells] += 1
        # "best" only once the EMA has settled a little, so one lucky first sample is not the reference
        settled = self.visits[cells] >= 2
        self.best[cells] = torch.where(settled, torch.minimum(self.best[cells], self.error[cells]), self.best[cells])
        return cells

    def accumulate_samples(self, pix: torch.Tensor, ids: torch.Tensor, error: torch.Tensor) -> None:
        """:meth:`accumulate` of the errors at flat pixels ``pix`` [M] of ``error`` [H W] (a view's samples from
        :meth:`locate`, ``ids`` their cells). On the CPU one compiled pass (same values), each (pix, ids) pair's
        cells and sample slots computed once."""
        if error.device.type != "cpu" or error.dtype != torch.float32 or self.error.dtype != torch.float32:
            self.accumulate(ids, error[pix])
            return
        from .cell_kernels import fold_cells

        plan = self._plans.get(id(ids))
        if plan is None or plan[0] is not ids:
            keep = ids >= 0
            cells, inv, counts = torch.unique(ids[keep], return_inverse=True, return_counts=True)
            if len(self._plans) > 4096:  # views dropped long ago
                self._plans.clear()
            plan = self._plans[id(ids)] = (ids, pix[keep].numpy(), inv.numpy(), cells.numpy(),
                                           counts.to(torch.float32).numpy())
        stats = self._stats
        if stats is None or stats[0] is not self.error or stats[1] is not self.best or stats[2] is not self.visits:
            stats = self._stats = (self.error, self.best, self.visits, self.error.numpy(), self.best.numpy(),
                                   self.visits.numpy())
        if plan[3].shape[0]:
            fold_cells(error.contiguous().numpy(), *plan[1:], float(self.cfg.ema), *stats[3:])

    def need(self, cells: torch.Tensor, good_error: float, regress_gain: float, regress_margin: float) -> torch.Tensor:
        """How much supervision each cell still needs: error above ``good_error`` plus a bonus for regression
        (running error risen more than ``regress_margin`` above its best)."""
        err = self.error[cells]
        regress = (err - self.best[cells] - regress_margin).clamp_min(0)
        regress = torch.where(torch.isfinite(regress), regress, torch.zeros_like(regress))
        return (err - good_error).clamp_min(0) + regress_gain * regress

    def state_dict(self) -> dict:
        n = len(self)
        return {"hash": self.hash.state_dict(), "error": self.error[:n].clone(), "best": self.best[:n].clone(),
                "visits": self.visits[:n].clone(), "coverage": self.coverage[:n].clone()}

    def load_state_dict(self, state: dict) -> None:
        self.hash.load_state_dict(state["hash"])
        self.error, self.best = state["error"].clone(), state["best"].clone()
        self.visits, self.coverage = state["visits"].clone(), state["coverage"].clone()
