"""Clocks that release a recorded stream to the Reconstructor.

- :class:`BudgetClock` (deterministic): every released source frame grants a fixed optimisation budget, so runs
  are reproducible on any machine (tests, ablations).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

from .frame import Frame


@dataclass
class ClockReport:
    released: int = 0
    integrated: int = 0
    dropped: int = 0
    dropped_indices: list[int] = field(default_factory=list)
    skipped_bad: list[str] = field(default_factory=list)


class BudgetClock:
    """Deterministic budget: ``updates_per_frame`` optimisation updates per released source frame."""

    name = "budget"

    def __init__(self, updates_per_frame: int):
        self.updates_per_frame = int(updates_per_frame)

    def run(self, rec, frames: Iterable[Frame], on_release: Callable[[Frame], None] | None = None) -> ClockReport:
        report = ClockReport()
        for frame in frames:
            report.released += 1
            if on_release is not None:
                on_release(frame)
            rec.integrate(frame, updates=self.updates_per_frame)
            report.integrated += 1
        return report
