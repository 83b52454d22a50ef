"""The one table of run options: each numeric option of ``eligsir map``, ``eligsir batch`` (its command line, its
manifest lines and :func:`~eligsir_o3d.batch.map_many`), ``eligsir demo`` and ``eligsir live`` has one entry here
with its type, its default and its range, so the commands agree on defaults and refuse the same values with the
same one-line message naming the option.

    check_option("eval_every", -5)      # ValueError: --eval-every -5: must be an integer >= 0 (0: only at the end)
    default("checkpoint_every")         # 50, for eligsir map and eligsir batch alike

The replay speed also has a floor that depends on the recording (:func:`check_speed_for`): the run may not ask
for more than :data:`MAX_MODELLED_S` seconds of mapping time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MAX_MODELLED_S = 30 * 24 * 3600.0  # seconds of mapping time a run may ask for (recording length / speed)


@dataclass(frozen=True)
class Option:
    """One run option: ``kind`` int or float; ``low``/``high`` its range (inclusive; ``low_open``: low itself
    excluded); ``none_ok``: None means "not given" (the config's, or unlimited); ``meaning`` ends the refusal."""

    kind: type
    default: object
    low: float
    high: float
    low_open: bool = False
    none_ok: bool = False
    meaning: str = ""

    def flag(self, name: str) -> str:
        return "--" + name.replace("_", "-")


OPTIONS: dict[str, Option] = {
    "max_frames": Option(int, None, 1, 10 ** 8, none_ok=True, meaning="use only the first N frames"),
    "holdout_every": Option(int, 8, 0, 10 ** 6, meaning="every N-th frame held out; 0: none"),
    "eval_every": Option(int, 100, 0, 10 ** 9, meaning="updates between held-out checkpoints; 0: only at the end"),
    "checkpoint_every": Option(int, 50, 0, 10 ** 9, meaning="source frames between checkpoints; 0: none"),
    "refine": Option(int, 0, 0, 10 ** 7, meaning="post-mapping updates"),
    "offline_updates": Option(int, 0, 0, 10 ** 9, meaning="0: 40 updates per source frame"),
    "updates_per_frame": Option(int, None, 0, 10 ** 5, none_ok=True, meaning="updates per source frame"),
    "speed": Option(float, None, 1e-6, 1e6, none_ok=True, meaning="replay speed; 0.1 gives 10x the recording's "
                    "duration"),
    "seed": Option(int, None, 0, 2 ** 63 - 1, none_ok=True, meaning="random seed"),
    "depth_max": Option(float, None, 0, 1e4, low_open=True, none_ok=True, meaning="metres"),
    "min_confidence": Option(int, None, 0, 2, none_ok=True, meaning="ARKit confidence 0, 1 or 2"),
    "frames": Option(int, None, 1, 10 ** 8, none_ok=True, meaning="frames to map"),
    "seconds": Option(float, None, 0, 10 ** 7, low_open=True, none_ok=True, meaning="seconds to map"),
    # eligsir export / render
    "voxel_size": Option(float, 0.02, 0, 100, low_open=True, meaning="TSDF voxel size in metres"),
    "min_opacity": Option(float, 0.1, 0, 1, meaning="opacity below which a Gaussian is dropped"),
    "fps": Option(float, 24.0, 0, 1000, low_open=True, meaning="video frames per second"),
    "smooth": Option(float, 0.0, 0, 10 ** 6, meaning="poses of path smoothing; 0: none"),
    # eligsir batch
    "cpus_per_task": Option(float, 1.0, 0, 4096, low_open=True, meaning="CPUs per sequence"),
    "gpus_per_task": Option(float, None, 0, 64, none_ok=True, meaning="GPUs per sequence"),
    "max_retries": Option(int, 3, 0, 100, meaning="retries of a sequence whose worker died"),
    "task_timeout": Option(float, 0.0, 0, 10 ** 7, meaning="seconds a sequence may take; 0: from the recording's "
                           "length and the speed"),
}


def default(name: str):
    """The default of option ``name`` (the same for every command that takes it)."""
    return OPTIONS[name].default


def check_option(name: str, value, flag: str | None = None):
    """``value`` of option ``name`` as its type, or ValueError naming the option (``flag``, default ``--name``)
    and its range. Booleans, NaN, infinities, fractions for an integer option and out-of-range values are
    refused."""
    opt = OPTIONS[name]
    flag = flag or opt.flag(name)
    if value is None:
        if opt.none_ok:
            return None
        raise ValueError(f"{flag}: a value is required ({opt.meaning})")
    what = "an integer" if opt.kind is int else "a number"
    rng = (f"> {opt.low:g}" if opt.low_open else f">= {opt.low:g}") + f" and <= {opt.high:g}"
    bad = ValueError(f"{flag} {value!r:.40}: must be {what} {rng} ({opt.meaning})")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        try:
            value = opt.kind(str(value).strip())
        except (TypeError, ValueError, OverflowError):
            raise bad from None
    if isinstance(value, float) and not math.isfinite(value):
        raise bad
    if opt.kind is int:
        if float(value) != int(value):
            raise bad
        value = int(value)
    if (value <= opt.low if opt.low_open else value < opt.low) or value > opt.high:
        raise bad
    return opt.kind(value)


def check_options(obj, names=None, flags: dict | None = None) -> None:
    """Check (and normalise in place) every attribute of ``obj`` that is an option of the table (or ``names``)."""
    for name in names or OPTIONS:
        if hasattr(obj, name):
            setattr(obj, name, check_option(name, getattr(obj, name), (flags or {}).get(name)))


def check_speed_for(speed: float, duration_s: float, what: str) -> None:
    """Refuse a replay ``speed`` that would give recording ``what`` (``duration_s`` seconds long) more than
    :data:`MAX_MODELLED_S` seconds of mapping time: the floor is duration / MAX_MODELLED_S."""
    if not (math.isfinite(duration_s) and duration_s > 0):
        return
    floor = duration_s / MAX_MODELLED_S
    if not speed >= floor:
        raise ValueError(f"--speed {speed:g}: {what} lasts {duration_s:.1f} s, so the run would map for "
                         f"{duration_s / speed:.3g} s; the slowest speed for it is {floor:.3g} "
                         f"({MAX_MODELLED_S / 86400:.0f} days of mapping time)")
