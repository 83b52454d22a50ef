"""The cost model: modelled seconds of the mapper's work, and its fit to measured timings.

The deterministic clocks replay a recording against this model instead of the wall clock, so that backlog, drops
and the fidelity controller's decisions are reproducible. The model is a handful of non-negative constants; the
shipped ones (the dataclass defaults) were fitted on the project's reference machine, :mod:`.calibrate` fits the
machine a run is on, and a JSON file of the constants pins one (``eligsir map --cost-model FILE``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

UPDATE_TERMS = ("update_s", "gaussian_s", "pixel_s", "pixel_gaussian_s")


@dataclass
class CostModel:
    """Modelled seconds of the mapper's work. One update of ``pixels`` supervised pixels over ``gaussians``
    Gaussians (a view-culled update: the Gaussians in its view, :func:`priced_gaussians`; else the map's total):
    ``update_s + gaussian_s * gaussians + pixels * (pixel_s + pixel_gaussian_s * gaussians)`` (projection and Adam
    grow with N; blending grows with pixels times the Gaussians overlapping each pixel). One integrated frame
    (admission render, growth): ``frame_s + gaussian_s * gaussians``.

    Defaults ("shipped"): ``python benchmarks/budget/cost_model.py --frames 300`` on the project's reference machine
    (2 cores, the ``cpu`` renderer on 2 threads, an otherwise idle machine, the default policies mapping the first
    300 frames of 7-Scenes redkitchen); each refit and its figures are in the lab notebook (lab: cost-model-fits).
    """

    update_s: float = 0.000795
    """Seconds of fixed work per update."""
    gaussian_s: float = 2.71e-7
    """Seconds per Gaussian per update (projection, Adam) and per integrated frame."""
    pixel_s: float = 8.6e-8
    """Seconds per supervised pixel per update."""
    pixel_gaussian_s: float = 1.75e-11
    """Seconds per supervised pixel per Gaussian per update (blending)."""
    frame_s: float = 0.00076
    """Seconds of fixed work per integrated frame (admission render, growth)."""

    @classmethod
    def fit(cls, updates: np.ndarray, frames: np.ndarray) -> "CostModel":
        """Fit to timings: ``updates`` rows ``(pixels, gaussians, seconds)``, ``frames`` rows ``(gaussians, seconds)``.

        Non-negative least squares on relative error (every update weighs the same whatever its size); the frame
        term shares ``gaussian_s`` and takes the mean remainder (the budget is a sum over frames).
        """
        u = np.asarray(updates, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(frames, dtype=np.float64).reshape(-1, 2)
        if len(u) < 4 or not np.all(u[:, 2] > 0):
            raise ValueError(f"need at least 4 update timings, all positive; got {len(u)}")
        P, G, t = u[:, 0], u[:, 1], u[:, 2]
        A = np.stack([np.ones_like(P), G, P, P * G], 1) / t[:, None]
        norm = np.maximum(np.linalg.norm(A, axis=0), 1e-300)  # columns span 10 orders of magnitude
        a = nnls(A / norm, np.ones_like(t)) / norm
        frame_s = float(np.mean(np.maximum(f[:, 1] - a[1] * f[:, 0], 0.0))) if len(f) else cls.frame_s
        return cls(update_s=float(a[0]), gaussian_s=float(a[1]), pixel_s=float(a[2]), pixel_gaussian_s=float(a[3]),
                   frame_s=frame_s)

    def update(self, pixels: int, gaussians: int) -> float:
        return self.update_s + self.gaussian_s * gaussians + pixels * (self.pixel_s + self.pixel_gaussian_s * gaussians)

    def scaled(self, factor: float) -> "CostModel":
        """This model with every term multiplied by ``factor`` (a machine ``factor`` times slower)."""
        return CostModel(**{k: v * float(factor) for k, v in self.to_dict().items()})

    def frame(self, gaussians: int) -> float:
        return self.frame_s + self.gaussian_s * gaussians

    def ratios(self, updates: np.ndarray) -> np.ndarray:
        """Predicted / measured seconds of each timed update (rows ``(pixels, gaussians, seconds)``)."""
        u = np.asarray(updates, dtype=np.float64).reshape(-1, 3)
        return np.array([self.update(int(p), int(g)) for p, g, _ in u]) / u[:, 2]

    # ---- files ------------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "cost model") -> "CostModel":
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = [k for k in data if k not in names]
        if unknown:
            raise ValueError(f"{where}: unknown cost-model term(s) {unknown}; the terms are {', '.join(names)}")
        try:
            values = {k: float(v) for k, v in data.items()}
        except (TypeError, ValueError):
            raise ValueError(f"{where}: every cost-model term must be a number") from None
        if any(v < 0 or not np.isfinite(v) for v in values.values()):
            raise ValueError(f"{where}: cost-model terms must be finite and non-negative")
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path) -> "CostModel":
        """A cost model from a JSON file: its terms, or a config file holding them under ``clock.cost`` (as
        ``benchmarks/budget/cost_model.py --json`` and the calibration cache write)."""
        from ..io.inputs import read_json

        path = Path(path)
        try:  # a regular file, size-capped
            data = read_json(path, "cost-model file")
        except ValueError as e:
            raise ValueError(f"{e} (expected a cost-model JSON file)") from None
        if isinstance(data, dict) and "clock" in data:
            data = data["clock"].get("cost", {}) if isinstance(data["clock"], dict) else {}
        elif isinstance(data, dict) and "model" in data:
            data = data["model"]
        if not isinstance(data, dict) or not data:
            raise ValueError(f"{path}: no cost-model terms found")
        return cls.from_dict(data, str(path))


def priced_gaussians(rec) -> int:
    """The Gaussians the cost model prices for ``rec``'s work: those its last update supervised (a view-culled
    update pays for the Gaussians in view, not the map's total: ``rec.last_in_view``), else the map's total."""
    seen = getattr(rec, "last_in_view", None)
    return len(rec.gmap) if seen is None else min(int(seen), len(rec.gmap))


def nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Non-negative least squares for a handful of unknowns: the best unconstrained solution over every subset of
    free variables that comes out non-negative (exact, 2^n small solves)."""
    n = A.shape[1]
    best, best_r = np.zeros(n), float(np.sum(b * b))
    for k in range(1, n + 1):
        for free in combinations(range(n), k):
            x_free = np.linalg.lstsq(A[:, free], b, rcond=None)[0]
            if np.any(x_free < 0):
                continue
            x = np.zeros(n)
            x[list(free)] = x_free
            r = float(np.sum((A @ x - b) ** 2))
            if r < best_r:
                best, best_r = x, r
    return best
