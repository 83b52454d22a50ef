"""The budget's configuration: which clock releases the stream, and every per-frame, drain and offline budget."""

from __future__ import annotations

from dataclasses import dataclass, field

from .cost import CostModel

DEFAULT_FRAME_PERIOD_S = 1.0 / 30.0  # a 30 Hz camera: the period assumed until timestamps say otherwise
CLOCK_MODES = ("cost", "updates", "realtime")
COST_SOURCES = ("config", "calibrate")


@dataclass
class ClockConfig:
    # cost: deterministic replay against the cost model (modelled time; backlog, drops);
    # updates: deterministic, ``updates_per_frame`` updates for every frame (no backlog);
    # realtime: replay against the wall clock
    mode: str = "cost"
    speed: float = 1.0  # replay speed: 0.25 releases frames at a quarter of the recorded rate
    queue_size: int = 4  # frames that may wait for the mapper; beyond it the oldest waiting frame is dropped
    min_updates_behind: int = 1  # updates granted to a frame integrated while others wait (the map keeps learning)
    on_bad_frame: str = "skip"  # skip | stop
    frame_period_s: float = DEFAULT_FRAME_PERIOD_S  # period of frames without timestamps, and before a clock runs
    updates_per_frame: int = 8  # mode "updates", and Reconstructor.integrate() without a clock
    drain_updates: int = 100  # finalize(): bounded drain after the stream (the paper's ME state)
    realtime_drain_fraction: float = 0.03  # realtime: the drain also stops after this share of the stream
    # offline reference: its schedule is this many updates per source frame (coarse to fine; what it reaches:
    # docs/measurements.md, "Offline reference")
    offline_updates_per_frame: int = 40
    offline_updates: int = 0  # offline reference: a fixed schedule length instead (0: per source frame)
    # offline reference: (scale, share) stages of its coarse-to-fine supervision, and the means' step size at the
    # schedule's end as a share of optim.lrs.means (log-linear decay, 3DGS's 100x; 1: constant; measured effect:
    # docs/measurements.md)
    offline_stages: tuple = ((0.25, 0.4), (0.5, 0.3), (1.0, 0.3))
    offline_means_lr_final: float = 0.01
    # where mode "cost" takes its model: "config" (``cost`` below: the shipped fit unless a file set it) or
    # "calibrate" (fit this machine, device and renderer, cached; see eligsir_o3d.budget.calibrate)
    cost_source: str = "config"
    cost: CostModel = field(default_factory=CostModel)
    # mode "cost": weight of each measured / modelled ratio of the mapper's work in a running correction of the cost
    # model (0: none, the run is deterministic). A calibration fits a dozen frames; the run's own work drifts from
    # it (larger maps, the views' bookkeeping, another process taking a core), so ``eligsir map`` with a calibrated
    # model turns this on and the budget follows what the work costs on this machine now (issue 32: K 200 frames,
    # measured / modelled 1.64 without it)
    cost_feedback: float = 0.0


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
