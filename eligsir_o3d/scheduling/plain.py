"""The plain policies that the ablations swap in: fixed-stride keyframes with uniform replay
(:mod:`.keyframes`), fixed native resolution (here), and new-space seeding with dense per-frame depth insertion
(:mod:`.seeding`). They are also the baseline behaviour."""

from __future__ import annotations

from .base import FidelityPolicy
from .keyframes import KeyframesConfig, StrideConfig, StrideKeyframes  # noqa: F401 (their earlier home)
from .seeding import NewSpaceSeeding, SeedingConfig, unsupported_mask  # noqa: F401


class FixedFidelity(FidelityPolicy):
    """Supervise at one fixed scale (1.0 = native resolution)."""

    name = "fixed"

    def __init__(self, scale: float = 1.0):
        self._scale = float(scale)

    def scale(self) -> float:
        return self._scale

    def counters(self) -> dict:
        return {"scale": self._scale}
