"""The settings of Map-Guided View Scheduling (:mod:`.views`): admission, the active and retained sets, priorities."""

from __future__ import annotations

from dataclasses import dataclass, field

from .microcells import MicrocellConfig


@dataclass
class ViewConfig:
    min_translation_m: float = 0.05
    """Metres: a candidate this near a retained view, and turned less than ``min_rotation_deg``, is a duplicate."""
    min_rotation_deg: float = 5.0
    """Degrees: the rotation half of the near-duplicate test (both thresholds shrink as the budget grows)."""
    spacing_updates: float = 13.5
    """Updates a frame buys (1/4 scale) above which the duplicate thresholds shrink by sqrt(this / u); 0: fixed."""
    min_novelty: float = 0.10
    """Admit a frame when at least this share of its depth is not explained by the map."""
    max_gap_s: float = 1.0
    """Seconds: admit the next non-redundant view when none was admitted for this long."""
    active_size: int = 16
    """Views in the active supervision set."""
    active_share: float = 0.5
    """Share of updates drawn from the active set; the rest replay retained views."""
    retained_replay: str = "stalest"
    """How the retained share picks its view: ``stalest`` (a round robin) or ``priority`` (drawn by priority)."""
    drain_replay: str = "stalest"
    """The drain after the stream: ``stalest`` replays every retained view in turn; ``policy`` as the stream."""
    refresh_every: int = 10
    """Updates between priority refreshes."""
    fresh_updates: int = 15
    """A newly admitted view keeps a linearly decaying priority bonus for this many of its updates."""
    fresh_bonus: float = 0.2
    """Priority bonus of a brand-new view (same units as a cell's need)."""
    good_error: float = 0.03
    """Photometric L1 below which a cell counts as well reconstructed."""
    good_quantile: float = 0.5
    """Or below this quantile of the measured cells' running errors, whichever is higher (0: ``good_error`` alone)."""
    regress_gain: float = 2.0
    """Weight of a cell's rise above its best running error in its need."""
    regress_margin: float = 0.01
    """Rises of a cell's error smaller than this (photometric L1) are noise, not regression."""
    priority_floor: float = 0.005
    """Lowest priority of a retained view: every one keeps a chance of replay."""
    max_views: int = 400
    """Retained views held in memory; beyond it the lowest-priority inactive view is evicted."""
    trace_max: int = 50000
    """Rows of the decision trace (views_trace.csv) kept; later events are only counted."""
    cells: MicrocellConfig = field(default_factory=MicrocellConfig)
    """The world-space microcells that carry the map's per-region error (``views.cells.*``)."""
