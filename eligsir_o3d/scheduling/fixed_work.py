"""Fixed per-frame work that scales with load (the paper's "degrade gracefully under load").

Load-Adaptive Fidelity makes an *update* cheaper when frames wait, but every integrated frame also pays fixed work
that does not shrink with the supervision scale: the support render of admission, the evidence voxel hash and
insertions of growth, view bookkeeping. On a slow machine that fixed work alone can outrun the frame rate, and the
clock then drops frames. :class:`LoadScaledChecks` decides, per integrated frame, how much of it the frame gets:

- no frame waits: every frame gets the full admission check (pose pre-filter, support render, novelty, max gap);
- frames wait (``backlog >= busy_backlog``): the full check runs on one frame in ``k``, ``k = 1 + backlog``
  (at most ``max_check_every``); the others get the pose pre-filter and the max-gap rule only (no render), and a
  frame the pre-filter rejects costs nothing else either way;
- a deeper backlog (``>= low_res_backlog``) or the fidelity controller at its lowest scale while frames wait: the
  support render (admission and growth) runs at ``low_res_factor`` of its scale;
- a backlog of ``shed_backlog`` frames or more: frames without the full check get no update while behind (the
  update is not lost: once the queue empties the clock spends the time on updates again), so the queue drains
  before the clock has to drop a frame.

With ``fixed_work.enabled = False`` every frame gets the full check at full resolution and its update (the behaviour before).
The policy has explicit state (frames since the last full check, counters) saved in checkpoints; it never looks at
the map, only at the backlog a clock reports (``Reconstructor.set_load``).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FixedWorkConfig:
    enabled: bool = True
    """Scale the per-frame fixed work with the backlog; false: every frame gets the full check."""
    busy_backlog: int = 1
    """Frames waiting at which full admission checks thin out."""
    max_check_every: int = 4
    """Under the heaviest load, one frame in this many gets the full check."""
    low_res_backlog: int = 2
    """Frames waiting at which the support render drops to ``low_res_factor`` of its scale."""
    low_res_factor: float = 0.5
    """Factor on the support render's scale under load (0.5: 1/4 of the source resolution becomes 1/8)."""
    shed_backlog: int = 3
    """Frames waiting at which frames without the full check get no update while the mapper is behind."""




@dataclass(frozen=True)
class FramePlan:
    """What one integrated frame gets: the full admission check (support render, novelty) or only the pose
    pre-filter and max-gap rule; the support render's scale factor; its updates while the mapper is behind."""

    check: bool = True
    probe_factor: float = 1.0
    update_behind: bool = True


FULL = FramePlan()


class LoadScaledChecks:
    """Per-frame plan of the fixed work from the backlog (see the module docstring)."""

    name = "load_scaled"

    def __init__(self, cfg: FixedWorkConfig | None = None):
        self.cfg = cfg or FixedWorkConfig()
        if self.cfg.max_check_every < 1 or not 0 < self.cfg.low_res_factor <= 1:
            raise ValueError(f"load: max_check_every must be >= 1 and low_res_factor in (0, 1], got "
                             f"{self.cfg.max_check_every} and {self.cfg.low_res_factor}")
        self.since_check = 0  # frames planned since the last one with the full check
        self.counts = {"checked": 0, "light": 0, "low_res": 0, "no_update": 0}

    def plan(self, backlog: int, at_lowest_scale: bool = False) -> FramePlan:
        """The plan for the next integrated frame, with ``backlog`` frames waiting behind it."""
        c = self.cfg
        if not c.enabled or backlog < c.busy_backlog:
            plan = FULL
        else:
            every = min(c.max_check_every, 1 + int(backlog))
            check = self.since_check + 1 >= every
            low = backlog >= c.low_res_backlog or at_lowest_scale
            plan = FramePlan(check=check, probe_factor=c.low_res_factor if low else 1.0,
                             update_behind=check or backlog < c.shed_backlog)
        self.since_check = 0 if plan.check else self.since_check + 1
        self.counts["checked" if plan.check else "light"] += 1
        self.counts["low_res"] += int(plan.probe_factor < 1.0)
        self.counts["no_update"] += int(not plan.update_behind)
        return plan

    def counters(self) -> dict:
        return {"enabled": self.cfg.enabled, **self.counts}

    def state_dict(self) -> dict:
        return {"since_check": self.since_check, "counts": dict(self.counts)}

    def load_state_dict(self, state: dict) -> None:
        self.since_check = int(state.get("since_check", 0))
        self.counts.update(state.get("counts", {}))
