"""The budget's configuration: which clock releases the stream, and every per-frame, drain and offline budget."""

from __future__ import annotations

from dataclasses import dataclass, field

from .cost import CostModel

DEFAULT_FRAME_PERIOD_S = 1.0 / 30.0  # a 30 Hz camera: the period assumed until timestamps say otherwise
CLOCK_MODES = ("cost", "updates", "realtime")
COST_SOURCES = ("config", "calibrate")


@dataclass
class ClockConfig:
    mode: str = "cost"
    """``cost`` (replay against the cost model's modelled time), ``updates`` (a fixed count per frame) or ``realtime``."""
    speed: float = 1.0
    """Replay speed: 0.25 releases frames at a quarter of the recorded rate."""
    queue_size: int = 4
    """Frames that may wait for the mapper; beyond it the oldest waiting frame is dropped."""
    min_updates_behind: int = 1
    """Updates granted to a frame integrated while others wait, so the map keeps learning."""
    on_bad_frame: str = "skip"
    """A frame that cannot be read: ``skip`` it (logged and counted) or ``stop`` the run."""
    frame_period_s: float = DEFAULT_FRAME_PERIOD_S
    """Seconds between frames without timestamps, and before a clock has seen two."""
    updates_per_frame: int = 8
    """Updates per frame in mode ``updates``, and for ``Reconstructor.integrate()`` without a clock."""
    drain_updates: int = 100
    """Updates of ``finalize()``'s bounded drain after the stream (the paper's mapping-end state)."""
    realtime_drain_fraction: float = 0.03
    """In mode ``realtime`` the drain also stops after this share of the stream's duration."""
    offline_updates_per_frame: int = 40
    """Offline reference: schedule length in updates per source frame."""
    offline_updates: int = 0
    """Offline reference: a fixed schedule length in updates instead (0: per source frame)."""
    offline_stages: tuple = ((0.25, 0.4), (0.5, 0.3), (1.0, 0.3))
    """Offline reference: (scale, share of the schedule) stages of its coarse-to-fine supervision."""
    offline_means_lr_final: float = 0.01
    """Offline reference: the means' step at the schedule's end as a share of ``optim.lrs.means`` (log-linear)."""
    cost_source: str = "config"
    """Mode ``cost`` takes its model from ``config`` (``cost`` below) or ``calibrate`` (fit this machine, cached)."""
    cost: CostModel = field(default_factory=CostModel)
    """The cost model's constants (the shipped fit unless a file or a calibration sets them)."""
    cost_feedback: float = 0.0
    """Weight of each measured / modelled work ratio in a running correction of the cost model (0: deterministic)."""


def check_clock_config(c: ClockConfig) -> None:
    if c.mode not in CLOCK_MODES:
        raise ValueError(f"clock.mode must be one of {', '.join(CLOCK_MODES)}, got {c.mode!r}")
    if not 0.0 <= c.cost_feedback <= 1.0:
        raise ValueError(f"clock.cost_feedback must lie in [0, 1], got {c.cost_feedback}")
    if c.on_bad_frame not in ("skip", "stop"):
        raise ValueError(f"clock.on_bad_frame must be 'skip' or 'stop', got {c.on_bad_frame!r}")
    if c.cost_source not in COST_SOURCES:
        raise ValueError(f"clock.cost_source must be one of {', '.join(COST_SOURCES)}, got {c.cost_source!r}")
    if not c.speed > 0:
        raise ValueError(f"clock.speed must be positive, got {c.speed}")
    if not c.frame_period_s > 0:
        raise ValueError(f"clock.frame_period_s must be positive, got {c.frame_period_s}")
    for name in ("updates_per_frame", "drain_updates", "offline_updates_per_frame", "offline_updates"):
        if int(getattr(c, name)) < 0:
            raise ValueError(f"clock.{name} must be >= 0, got {getattr(c, name)}")
    if not 0 < c.offline_means_lr_final <= 1:
        raise ValueError(f"clock.offline_means_lr_final must be in (0, 1], got {c.offline_means_lr_final}")


def offline_updates(c: ClockConfig, n_source: int) -> int:
    """Length of the offline reference's full-resolution schedule for ``n_source`` source frames."""
    return int(c.offline_updates) or int(c.offline_updates_per_frame) * int(n_source)
