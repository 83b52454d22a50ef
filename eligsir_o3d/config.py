"""Nested dataclass configuration: one place for defaults, written with every result as config.json."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .gaussians import LearningRates
from .optim import LossConfig
from .scheduling.plain import SeedingConfig, StrideConfig
from .budget.config import ClockConfig
from .scheduling.fidelity import FidelityConfig
from .scheduling.growth import GrowthConfig
from .scheduling.support import ProbeConfig
from .scheduling.views import ViewConfig


@dataclass
class OptimConfig:
    lrs: LearningRates = field(default_factory=LearningRates)
    loss: LossConfig = field(default_factory=LossConfig)
    refine_scale: float = 1.0  # refine(): supervision scale of post-mapping updates (+N PM)


@dataclass
class Config:
    device: str = "cpu"
    renderer: str = "auto"  # auto | torch | cpu | gsplat
    sh_degree: int = 0
    max_gaussians: int = 300_000
    depth_scale: float = 1000.0  # integer depth / depth_scale = metres (Open3D's spelling)
    depth_max: float = 8.0  # metres; farther depth counts as no measurement
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    ablate: tuple[str, ...] = ()  # any of: scheduling, fidelity, growth (each swaps in the plain policy)
    fixed_scale: float = 1.0  # supervision scale when fidelity is ablated (1.0 = native, as in the paper)
    optim: OptimConfig = field(default_factory=OptimConfig)
    stride: StrideConfig = field(default_factory=StrideConfig)
    seeding: SeedingConfig = field(default_factory=SeedingConfig)
    views: ViewConfig = field(default_factory=ViewConfig)  # Map-Guided View Scheduling
    fidelity: FidelityConfig = field(default_factory=FidelityConfig)  # Load-Adaptive Fidelity
    growth: GrowthConfig = field(default_factory=GrowthConfig)  # Targeted Geometry Growth (+ 3DGS-MCMC)
    support: ProbeConfig = field(default_factory=ProbeConfig)  # the low-res support render admission and growth share
    clock: ClockConfig = field(default_factory=ClockConfig)  # the budget: clock mode, per-frame/drain/offline budgets

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2))

    @classmethod
    def from_dict(cls, data: dict) -> "Config":
        return _build(cls, data)

    @classmethod
    def load(cls, path: str | Path) -> "Config":
        return cls.from_dict(json.loads(Path(path).read_text()))


def _build(tp, data: Any):
    """Recursively rebuild a dataclass from a dict, ignoring unknown keys (older/newer config files)."""
    if not dataclasses.is_dataclass(tp) or not isinstance(data, dict):
        return data
    kwargs = {}
    hints = {f.name: f for f in dataclasses.fields(tp)}
    for name, f in hints.items():
        if name not in data:
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        value = data[name]
        if dataclasses.is_dataclass(default):
            value = _build(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return tp(**kwargs)
