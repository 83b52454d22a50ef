"""Moved: the clocks, the cost model and the clock configuration live in :mod:`eligsir_o3d.budget`.

This module only keeps ``from eligsir_o3d.clock import ...`` working for existing scripts."""

from .budget import BudgetClock, ClockConfig, ClockReport, CostModel, RealtimeClock, get_clock  # noqa: F401
