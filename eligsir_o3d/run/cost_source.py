"""Which cost model prices a run's budget (``--clock cost``), and the calibration ``eligsir map`` runs by default:
the rule is :data:`~.options.COST_MODEL_RULE`. Calibration times the first :data:`CALIBRATION_FRAMES` readable
source frames, consecutive as a stream delivers them, under the run's one bad-frame rule."""

from __future__ import annotations

import logging

from ..core.frame import Frame
from .frame_faults import BAD_FRAME_ERRORS, frame_fault

log = logging.getLogger("eligsir_o3d")

CALIBRATION_FRAMES = 12  # consecutive source frames that eligsir map times to fit the cost model
CALIBRATED_FEEDBACK = 0.05  # clock.cost_feedback of a calibrated run that sets none: the budget follows the work


def run_cost_model(rec, seq, source: list[int], path, *, offline: bool) -> dict:
    """Calibrate ``rec``'s cost model when its config asks for it (then the config records the fitted terms, so the
    results folder reruns with the same budget); returns which model the budget used, for metrics.json."""
    from ..budget import CostModel

    c = rec.config.clock
    if c.mode != "cost" or offline:
        return {"source": None}
    if c.cost_source == "calibrate":
        # consecutive frames, as a stream delivers them: frames picked far apart are each mostly new space,
        # and their seeding made the fitted per-frame cost 2-3x what a stream pays (less budget than real)
        frames = calibration_frames(seq, source, rec.config, path)
        model, info = rec.calibrate(frames, n_frames=len(frames))
        c.cost, c.cost_source = model, "config"
        if c.cost_feedback == 0:
            # the fit is a dozen frames' worth; the run's own measured work corrects it from then on (so the
            # budget is what this machine spends: a calibrated run is this machine's, not a reproducible one)
            c.cost_feedback = CALIBRATED_FEEDBACK
        log.info("cost model: calibrated for this machine (%s)", info.get("cache"))
        return info
    return {"source": "shipped" if c.cost == CostModel() else "config"}


def calibration_frames(seq, source: list[int], config, path) -> list[Frame]:
    """The first :data:`CALIBRATION_FRAMES` readable source frames. A bad frame follows the one rule
    (``clock.on_bad_frame``): skipped with a warning (the stream reports it again when it reaches it), or the run
    stops."""
    frames = []
    for i in source:
        if len(frames) == CALIBRATION_FRAMES:
            break
        try:
            frames.append(seq.frame(i, depth_max=config.depth_max))
        except BAD_FRAME_ERRORS as e:
            frame_fault(i, e, config.clock.on_bad_frame, "cost-model calibration: not timing")
    if not frames:
        raise ValueError(f"{path}: no source frame can be read to calibrate the cost model")
    return frames
