"""Regional quality of the paper's "Evaluation Protocol": fixed world-space cells, CVQ(t), CUC@Q(t).

Definitions (paper, "Regional quality"), implemented exactly:
- Cells: a fixed partition of world space into ``cell_size`` (0.5 m) cubes, key = floor(x / cell_size) as Int32 [3],
  stored on an Open3D ``core.HashMap`` (CPU) whose value is a dense cell id.
- Omega_c: a fixed set of held-out reference samples (view, pixel, reference depth), built once from the held-out
  frames: every ``sample_stride``-th pixel in u and v with valid depth is back-projected with the held-out pose, and
  the sample belongs to the cell containing its 3D point.
- Measurable: |Omega_c| >= ``min_samples`` (300) AND the samples come from >= ``min_views`` (2) distinct held-out views.
  Fixed once built; note that |Omega_c| counts subsampled pixels, so it depends on ``sample_stride``.
- Eligible: from t_vis(c), the first checkpoint after the cell's surface was observed from >= ``min_source_views`` (2)
  distinct SOURCE views. Observation = a released source frame's valid depth (every ``source_stride``-th pixel,
  default = ``sample_stride``), back-projected with its pose, lands in the cell. Held-out frames never count. It depends only on the released stream, never on the mapper.
- M(t) = eligible and measurable cells. e_c(t) = mean over Omega_c and RGB of the squared error of the render at t;
  q_c(t) = -10 log10(max(e_c, 1e-12)); CVQ(t) = mean of q_c over M(t); CUC@Q(t) = fraction of M(t) with q_c >= Q.
  When M(t) is empty, CVQ and CUC are undefined and reported as None.
- Missing renders count as failures: a missing view contributes squared error 1.0 (the maximum on [0, 1]) for each
  of its samples; non-finite rendered colour likewise.
"""

from __future__ import annotations

import numpy as np
import open3d.core as o3c
import torch

from ..core.frame import Frame
from ..core.voxels import unique_keys
from .metrics import EPS, squared_errors




class RegionalQuality:
    """Cell grid with fixed held-out sample sets, source-view eligibility and per-checkpoint cell PSNR."""

    def __init__(self, heldout_frames: list[Frame], cell_size: float = 0.5, min_samples: int = 300,
                 min_views: int = 2, quality_threshold: float = 20.0, sample_stride: int = 4,
                 min_source_views: int = 2, source_stride: int | None = None):
        if cell_size <= 0:
            raise ValueError(f"cell_size must be positive, got {cell_size}")
        if sample_stride < 1:
            raise ValueError(f"sample_stride must be >= 1, got {sample_stride}")
        self.cell_size = float(cell_size)
        self.min_samples, self.min_views = int(min_samples), int(min_views)
        self.min_source_views = int(min_source_views)
        self.quality_threshold = float(quality_threshold)
        self.sample_stride = int(sample_stride)
        self.source_stride = int(source_stride or sample_stride)
        self.heldout_indices = {int(f.index) for f in heldout_frames}
        self._build(heldout_frames)
        self.checkpoints = 0  # number of checkpoints evaluated so far

    # --- Omega_c: built once from the held-out frames ------------------------------------------------------------
    def _cell_keys(self, frame: Frame, stride: int, depth: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Int32 cell keys [M, 3], flat pixel indices [M] and reference depths [M] of a frame's valid depth
        (``depth``: the frame's [H, W] depth when already decoded)."""
        depth = frame.depth if depth is None else depth
        pts_cam, pix = frame.camera.backproject(depth, stride)  # [M, 3], [M]
        T = torch.as_tensor(frame.T_world_cam, dtype=torch.float64)
        pts_world = pts_cam.double() @ T[:3, :3].T + T[:3, 3]
        keys = torch.floor(pts_world / self.cell_size).to(torch.int32)
        return keys, pix, depth.reshape(-1)[pix]

    def _build(self, frames: list) -> None:
        # Deduplicated per view first (a view's samples touch few cells), so only one view's points exist at a
        # time; the union of the views' cells, deduplicated again, gives the same cells in the same (code) order.
        per_view, shapes = [], []
        for f in frames:  # one view's depth decoded at a time
            depth = f.depth
            view_keys, view_inverse = unique_keys(self._cell_keys(f, self.sample_stride, depth)[0])
            per_view.append((view_keys, view_inverse.to(_small_int(view_keys.shape[0]))))
            shapes.append(tuple(int(x) for x in depth.shape))
            del depth
        all_keys = torch.cat([k for k, _ in per_view]) if per_view else torch.zeros(0, 3, dtype=torch.int32)
        keys, inverse = unique_keys(all_keys)  # dedupe before the hash-map insert (duplicates break it)
        del all_keys
        self.keys = keys  # [C, 3] int32
        n_cells = keys.shape[0]
        self.hashmap = o3c.HashMap(max(n_cells, 1), key_dtype=o3c.int32, key_element_shape=(3,),
                                   value_dtype=o3c.int32, value_element_shape=(1,), device=o3c.Device("CPU:0"))
        if n_cells:
            self.hashmap.insert(o3c.Tensor(keys.numpy()), o3c.Tensor(np.arange(n_cells, dtype=np.int32)[:, None]))
        # Samples grouped by view: the cell id of each sample, in the order of the view's valid strided pixels.
        # No pixel indices and no colour are copied: both come from the view's own images when it is evaluated
        # (sample_pixels(depth, stride) gives the pixels back), so a sample costs 2 bytes (4 beyond 32,767 cells).
        cell_dtype = _small_int(n_cells)
        self.samples: list[dict] = []
        n_samples = torch.zeros(n_cells, dtype=torch.long)
        n_views = torch.zeros(n_cells, dtype=torch.long)
        start = 0
        for f, (view_keys, view_inverse), shape in zip(frames, per_view, shapes):
            cell = inverse[start:start + view_keys.shape[0]][view_inverse.long()]  # [M_v] global cell ids
            start += view_keys.shape[0]
            self.samples.append({"cell": cell.to(cell_dtype), "index": int(f.index), "shape": shape})
            n_samples += torch.bincount(cell, minlength=n_cells)
            n_views[torch.unique(cell)] += 1
        self.views = list(frames)  # the caller's objects (no copy): their images are read when evaluated
        self.n_samples, self.n_views = n_samples, n_views  # [C]
        self.measurable = (n_samples >= self.min_samples) & (n_views >= self.min_views)  # [C] bool, fixed
        # Eligibility state: distinct source views seen per cell (saturating at 2) and t_vis (-1 = not yet).
        self._first_source = torch.full((n_cells,), -1, dtype=torch.long)
        self.n_source_views = torch.zeros(n_cells, dtype=torch.long)
        self.t_vis = torch.full((n_cells,), -1, dtype=torch.long)
        self.q = torch.full((n_cells,), float("nan"), dtype=torch.float64)  # latest cell PSNR [C]

    def samples_nbytes(self, view: int) -> int:
        """Bytes the regional samples of held-out view ``view`` hold (its cell ids)."""
        c = self.samples[view]["cell"]
        return int(c.numel() * c.element_size())

    def cell_ids(self, keys: torch.Tensor) -> torch.Tensor:
        """Dense cell ids [M] of Int32 keys [M, 3]; -1 where the cell holds no held-out sample."""
        if keys.shape[0] == 0 or self.keys.shape[0] == 0:
            return torch.full((keys.shape[0],), -1, dtype=torch.long)
        buf, found = self.hashmap.find(o3c.Tensor(keys.contiguous().numpy()))
        values = torch.from_numpy(self.hashmap.value_tensor().numpy()[:, 0].astype(np.int64))  # fetched after insert
        buf = torch.from_numpy(buf.numpy().astype(np.int64))
        found = torch.from_numpy(found.numpy())
        return torch.where(found, values[buf.clamp_min(0)], torch.full_like(buf, -1))

    # --- eligibility ---------------------------------------------------------------------------------------------
    def observe_source(self, frame: Frame) -> bool:
        """Record the cells a released SOURCE frame's depth surface touches. Held-out frames are ignored (False).

        Distinct views are told apart by ``frame.index``; observing the same frame twice counts once. Only cells that
        hold held-out samples are tracked: no other cell can ever be measurable.
        """
        if int(frame.index) in self.heldout_indices:
            return False
        keys, _, _ = self._cell_keys(frame, self.source_stride)
        ids = self.cell_ids(unique_keys(keys)[0])
        ids = ids[ids >= 0]
        view = int(frame.index)
        first = self._first_source[ids]
        new = first < 0
        self._first_source[ids[new]] = view
        self.n_source_views[ids[new]] = 1
        other = (~new) & (first != view)
        self.n_source_views[ids[other]] = torch.clamp_min(self.n_source_views[ids[other]], 2)
        return True

    @property
    def eligible(self) -> torch.Tensor:  # [C] bool
        return self.t_vis >= 0

    def _update_eligibility(self) -> None:
        newly = (self.t_vis < 0) & (self.n_source_views >= self.min_source_views)
        self.t_vis[newly] = self.checkpoints

    # --- one checkpoint ------------------------------------------------------------------------------------------
    def accumulate(self, view: int, color, ref_color: torch.Tensor | None = None,
                   ref_depth: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-cell (sum of squared errors, number of sample-channels) of held-out view ``view`` rendered as ``color``.

        ``color`` [H, W, 3] or None (missing render: squared error 1.0 for every sample). ``ref_color`` [H, W, 3]
        and ``ref_depth`` [H, W]: the view's own images when the caller has them decoded already (else read here).
        """
        s = self.samples[view]
        n_cells = self.keys.shape[0]
        cell = s["cell"].long()
        if color is None:
            se = torch.ones(cell.shape[0], dtype=torch.float64)
        else:
            pred = torch.as_tensor(color).detach().to("cpu", torch.float32)
            if tuple(pred.shape[:2]) != s["shape"]:
                raise ValueError(f"held-out view {s['index']}: render is {tuple(pred.shape[:2])}, "
                                 f"reference is {s['shape']}")
            f = self.views[view]
            ref_depth = f.depth if ref_depth is None else ref_depth
            ref_color = f.color if ref_color is None else ref_color
            pix = sample_pixels(ref_depth, self.sample_stride)
            if pix.shape[0] != cell.shape[0]:
                raise ValueError(f"held-out view {s['index']}: its depth changed since the samples were built "
                                 f"({pix.shape[0]} valid sample pixels, {cell.shape[0]} samples)")
            picked = pred.reshape(-1, 3)[pix]  # [M_v, 3]
            ref = ref_color.reshape(-1, 3)[pix].float()
            se = squared_errors(picked[:, None], ref[:, None])[:, 0].sum(-1).double() / 3.0
        sums = torch.zeros(n_cells, dtype=torch.float64).index_add_(0, cell, se)
        return sums, torch.bincount(cell, minlength=n_cells)

    def begin(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Zeroed per-cell accumulators (sums float64 [C], counts long [C]) of one checkpoint: add each view's
        :meth:`accumulate` into them, then :meth:`finish`. Views can so be scored one at a time, their renders
        dropped as soon as they are scored."""
        n_cells = self.keys.shape[0]
        return torch.zeros(n_cells, dtype=torch.float64), torch.zeros(n_cells, dtype=torch.long)

    def finish(self, sums: torch.Tensor, counts: torch.Tensor) -> dict:
        """Close one checkpoint from the accumulated per-cell sums and counts: update eligibility, then q_c, CVQ
        and CUC@Q (see :meth:`summary`)."""
        self._update_eligibility()
        self.checkpoints += 1
        e = sums / counts.clamp_min(1)  # e_c: mean over samples of the per-sample RGB mean squared error
        self.q = torch.where(counts > 0, -10.0 * torch.log10(e.clamp_min(EPS)), torch.full_like(e, float("nan")))
        return self.summary()

    def evaluate(self, colors: list) -> dict:
        """Close one checkpoint: update eligibility, then compute q_c, CVQ and CUC@Q from held-out renders.

        colors: one entry per held-out view, in the order given at construction: [H, W, 3] in [0, 1] or None.
        """
        if len(colors) != len(self.samples):
            raise ValueError(f"expected {len(self.samples)} held-out renders, got {len(colors)}")
        sums, counts = self.begin()
        for v, color in enumerate(colors):
            s, c = self.accumulate(v, color)
            sums += s
            counts += c
        return self.finish(sums, counts)

    def summary(self) -> dict:
        """CVQ and CUC@Q over M(t) from the latest evaluation (None when M(t) is empty)."""
        m = self.eligible & self.measurable
        q = self.q[m]
        n = int(m.sum())
        cvq = float(q.mean()) if n else None
        cuc = float((q >= self.quality_threshold).double().mean()) if n else None
        return {"cvq": cvq, "cuc": cuc, "n_evaluable": n, "n_eligible": int(self.eligible.sum()),
                "n_measurable": int(self.measurable.sum()), "n_cells": int(self.keys.shape[0])}

    def cell_table(self, up_axis: int = 2) -> dict:
        """Per-cell record for plots and metrics.json (cells with held-out samples only)."""
        return {
            "cell_size": self.cell_size,
            "up_axis": int(up_axis),
            "quality_threshold": self.quality_threshold,
            "keys": self.keys.tolist(),
            "q": [None if not np.isfinite(x) else round(float(x), 4) for x in self.q.tolist()],
            "n_samples": self.n_samples.tolist(),
            "n_views": self.n_views.tolist(),
            "eligible": self.eligible.tolist(),
            "measurable": self.measurable.tolist(),
            "t_vis": self.t_vis.tolist(),
        }


def _small_int(n: int) -> torch.dtype:
    """The smallest signed integer dtype that holds ids 0 .. n - 1 (int16, else int32)."""
    return torch.int16 if n <= torch.iinfo(torch.int16).max else torch.int32


def sample_pixels(depth: torch.Tensor, stride: int) -> torch.Tensor:
    """Flat pixel indices [M] (long) of the valid (> 0) pixels of ``depth`` [H, W] on the ``stride`` grid, in the
    order of :meth:`Camera.backproject <eligsir_o3d.core.camera.Camera.backproject>` (row-major)."""
    w = depth.shape[1]
    grid = depth[::stride, ::stride]
    v, u = torch.nonzero(grid > 0, as_tuple=True)
    return (v * stride) * w + u * stride


def cvq_auc(progress: list[float], cvq: list[float | None]) -> float | None:
    """CVQ-AUC = (1 / (p_max - p_min)) * integral of CVQ(p) dp over normalised source progress (trapezoid rule).

    progress: p = N_released / N_total of each checkpoint; cvq: CVQ at that checkpoint, None or NaN where M(t) was
    empty. Undefined checkpoints are dropped, so the integral runs from the first checkpoint with a defined CVQ to
    the last one ([p_min, p_max] of the defined points). Points are taken in order of progress (stable, so
    checkpoints at equal progress keep their chronological order and form a vertical step of zero area).
    One defined point -> its value; several at the same progress -> their mean; none -> None.
    """
    if len(progress) != len(cvq):
        raise ValueError(f"progress and cvq differ in length: {len(progress)} vs {len(cvq)}")
    pts = [(float(p), float(c)) for p, c in zip(progress, cvq)
           if p is not None and c is not None and np.isfinite(p) and np.isfinite(c)]
    if not pts:
        return None
    p, c = np.array(pts).T
    order = np.argsort(p, kind="stable")
    p, c = p[order], c[order]
    span = p[-1] - p[0]
    if span <= 0:
        return float(c.mean())
    return float(np.sum(0.5 * (c[1:] + c[:-1]) * np.diff(p)) / span)
