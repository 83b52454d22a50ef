"""The budget: how much compute the mapper gets, and against which clock.

- :mod:`.cost`: the :class:`CostModel` (modelled seconds of an update and of a frame) and its non-negative fit;
- :mod:`.calibrate`: timing a few updates per supervision scale on this machine, device and renderer, and a
  cache of the fitted model;
- :mod:`.clocks`: the clocks that release a stream (wall clock, modelled time, fixed updates) and bound the drain;
- :mod:`.config`: ``clock.mode = cost | updates | realtime`` and every per-frame, drain and offline budget, and
  the one default frame period (30 Hz).
"""

from __future__ import annotations

from .clocks import BudgetClock, ClockReport, RealtimeClock
from .clock import CLOCK_MODES, DEFAULT_FRAME_PERIOD_S, ClockConfig, check_clock_config, offline_updates
from .cost import CostModel

__all__ = ["BudgetClock", "CLOCK_MODES", "ClockConfig", "ClockReport", "CostModel", "DEFAULT_FRAME_PERIOD_S",
           "RealtimeClock", "check_clock_config", "get_clock", "offline_updates"]


def get_clock(cfg, cost: CostModel | None = None, offline: bool = False):
    """The clock a :class:`Config` asks for (``cfg.clock``). ``cost``: the model the cost clock prices updates with
    (default ``cfg.clock.cost``). ``offline``: the offline reference's (every frame integrated, no updates while
    streaming; its schedule runs after the stream)."""
    c = cfg.clock
    check_clock_config(c)
    common = dict(speed=c.speed, queue_size=c.queue_size, min_updates_behind=c.min_updates_behind,
                  on_bad_frame=c.on_bad_frame, frame_period_s=c.frame_period_s)
    if offline:
        return BudgetClock(0, on_bad_frame=c.on_bad_frame, frame_period_s=c.frame_period_s)
    if c.mode == "realtime":
        return RealtimeClock(drain_fraction=c.realtime_drain_fraction, **common)
    if c.mode == "updates":
        return BudgetClock(c.updates_per_frame, c.cost if cost is None else cost, **common)
    return BudgetClock(None, c.cost if cost is None else cost, feedback=c.cost_feedback,
                       drain_updates=c.drain_updates, **common)
