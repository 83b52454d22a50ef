"""The offline reference's schedule, whose length is known in advance: coarse-to-fine supervision (DashGaussian-style:
the first updates at a coarse scale, where an update is cheap and fits the low frequencies, the last ones at full
resolution) and an exponential decay of the means' step size over the schedule (3DGS's position-lr schedule).

Measured on the real recordings at hand, a fixed number of updates buys more held-out quality when most of them are
coarse (see :data:`DEFAULT_STAGES`); the schedule also costs less time, so a fixed time buys more updates.
"""

from __future__ import annotations

from .base import FidelityPolicy

# (scale, share of the schedule), in order; the shares add up to 1
DEFAULT_STAGES: tuple[tuple[float, float], ...] = ((0.25, 0.4), (0.5, 0.3), (1.0, 0.3))


class CoarseToFine(FidelityPolicy):
    """Scale of the next update from the progress through a ``total``-update schedule, stage by stage."""

    name = "coarse_to_fine"

    def __init__(self, total: int, stages: tuple[tuple[float, float], ...] = DEFAULT_STAGES):
        if total < 1:
            raise ValueError(f"coarse-to-fine schedule: total updates must be >= 1, got {total}")
        stages = tuple(tuple(s) for s in stages)
        if not stages or any(len(s) != 2 for s in stages):
            raise ValueError(f"coarse-to-fine stages must be (scale, share) pairs, got {stages}")
        shares = [float(s) for _, s in stages]
        if any(not 0 < sc <= 1 for sc, _ in stages) or any(s < 0 for s in shares) or abs(sum(shares) - 1.0) > 1e-6:
            raise ValueError(f"coarse-to-fine stages must be (scale in (0, 1], share >= 0) with shares summing "
                             f"to 1, got {stages}")
        self.total = int(total)
        self.stages = tuple((float(sc), float(s)) for sc, s in stages)
        self.updates = 0
        self.by_scale: dict[str, int] = {}

    @property
    def progress(self) -> float:
        """Share of the schedule done, in [0, 1]."""
        return min(self.updates / self.total, 1.0)

    def scale(self) -> float:
        p = self.updates / self.total
        edge = 0.0
        for sc, share in self.stages:
            edge += share
            if p < edge - 1e-12:
                return sc
        return self.stages[-1][0]

    def observe(self, seconds: float, pixels: int, backlog: int) -> None:
        key = f"{self.scale():g}"
        self.by_scale[key] = self.by_scale.get(key, 0) + 1
        self.updates += 1

    def counters(self) -> dict:
        return {"total": self.total, "stages": [list(s) for s in self.stages], "updates_by_scale": dict(self.by_scale)}

    def state_dict(self) -> dict:
        return {"updates": self.updates, "by_scale": dict(self.by_scale)}

    def load_state_dict(self, state: dict) -> None:
        self.updates = int(state["updates"])
        self.by_scale = dict(state.get("by_scale", {}))


def decayed_lr(lr0: float, final_ratio: float, progress: float) -> float:
    """Log-linear interpolation from ``lr0`` (progress 0) to ``lr0 * final_ratio`` (progress 1), as 3DGS decays
    its position step size over a schedule of known length."""
    p = min(max(float(progress), 0.0), 1.0)
    return float(lr0) * float(final_ratio) ** p


class MeansLrDecay:
    """An update callback (``Reconstructor.callbacks``) that sets the means' Adam step size for the next update from
    the progress of a :class:`CoarseToFine` schedule: ``lrs.means`` at the start, ``final_ratio`` times it at the end.
    The start value is read from the map's learning rates, so a configured ``optim.lrs.means`` still applies."""

    def __init__(self, schedule: CoarseToFine, final_ratio: float):
        if not 0 < final_ratio <= 1:
            raise ValueError(f"clock.offline_means_lr_final must be in (0, 1], got {final_ratio}")
        self.schedule = schedule
        self.final_ratio = float(final_ratio)

    def lr(self, lr0: float) -> float:
        return decayed_lr(lr0, self.final_ratio, self.schedule.progress)

    def __call__(self, rec) -> None:
        gmap = rec.gmap
        gmap.adam.lr["means"] = self.lr(gmap.lrs.means)


def install_means_lr_decay(rec, schedule: CoarseToFine, means_lr_final: float) -> None:
    """When ``means_lr_final`` < 1, decay the means' step size over ``schedule`` to that share of ``lrs.means``: an
    update callback on ``rec``, applied once now for the first update (progress 0, or a resumed schedule's)."""
    if means_lr_final < 1:
        decay = MeansLrDecay(schedule, means_lr_final)
        rec.callbacks.append(decay)
        decay(rec)


def offline_schedule(rec, total: int, stages=DEFAULT_STAGES, means_lr_final: float = 1.0) -> CoarseToFine:
    """Install the offline reference's schedule on an existing ``rec`` (coarse-to-fine supervision over ``total``
    updates and the means' step-size decay). The offline run itself builds it at construction instead
    (``Reconstructor(..., offline_frames=n)``, ``get_policies(cfg, offline=True)``)."""
    policy = CoarseToFine(total, stages)
    rec.fidelity = policy
    install_means_lr_decay(rec, policy, means_lr_final)
    return policy
