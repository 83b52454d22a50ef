"""The conditions a cost-model calibration is taken under. A fit timed while another job ran
prices every update too high, and every later run on the machine would get too small a budget; so each cached fit
records its conditions, and :func:`~.calibrate.cached_cost_model` refuses to reuse one that looks wrong:

- **busy**: the 1-minute load average per CPU was above :data:`MAX_LOAD_PER_CPU`, or a quick quiet-machine check
  (a fixed CPU loop timed :data:`QUIET_REPEATS` times) spread by more than :data:`MAX_SPREAD`. A busy fit is used
  for the run that took it (with a warning) and never reused: the next run calibrates again.
- **stale**: older than :data:`MAX_AGE_DAYS`, or taken under another kernel (the machine key already holds the
  host, CPU, device, renderer, torch and package versions: another one is another cache file).

Readings come from :data:`READERS` (replaceable in tests: the real load of a shared machine is not a test input).
"""

from __future__ import annotations

import os
import platform
import time

MAX_LOAD_PER_CPU = 0.75
MAX_SPREAD = 1.5  # slowest / fastest of the quiet check's repeats
QUIET_REPEATS = 5
MAX_AGE_DAYS = 30.0


def _quiet_check() -> float:
    """Slowest / fastest time of a fixed ~5 ms CPU loop, repeated: near 1 on a quiet machine."""
    times = []
    for _ in range(QUIET_REPEATS):
        t0 = time.perf_counter()
        x = 0
        for i in range(60_000):
            x += i * i
        times.append(time.perf_counter() - t0)
    return max(times) / max(min(times), 1e-9)


READERS = {"load": lambda: os.getloadavg()[0], "spread": _quiet_check, "cpus": lambda: os.cpu_count() or 1,
           "kernel": platform.release, "now": time.time}


def measure() -> dict:
    """The conditions now: {"load_1m", "cpus", "spread", "kernel", "taken" (unix seconds), "busy" (reason|None)}."""
    c = {"load_1m": float(READERS["load"]()), "cpus": int(READERS["cpus"]()), "spread": float(READERS["spread"]()),
         "kernel": str(READERS["kernel"]()), "taken": float(READERS["now"]())}
    c["busy"] = busy_reason(c)
    return c


def busy_reason(c: dict) -> str | None:
    if c["load_1m"] / max(c["cpus"], 1) > MAX_LOAD_PER_CPU:
        return f"load average {c['load_1m']:.1f} on {c['cpus']} CPU(s)"
    if c["spread"] > MAX_SPREAD:
        return f"a fixed CPU loop's time varied {c['spread']:.1f}x (another job competes for the CPU)"
    return None


def unusable_reason(recorded: dict | None, max_age_days: float = MAX_AGE_DAYS) -> str | None:
    """Why a cached fit with these recorded conditions must not be reused (None: it may)."""
    if not isinstance(recorded, dict) or "taken" not in recorded:
        return "it records no calibration conditions (an older cache file)"
    if recorded.get("busy"):
        return f"it was taken on a busy machine ({recorded['busy']})"
    age = (float(READERS["now"]()) - float(recorded["taken"])) / 86400.0
    if age > max_age_days:
        return f"it is {age:.0f} days old (more than {max_age_days:g})"
    if recorded.get("kernel") != str(READERS["kernel"]()):
        return f"it was taken under kernel {recorded.get('kernel')} (now {READERS['kernel']()})"
    return None
