"""Values no run can use, refused when a Config is resolved, whichever way they came in
(``--set``, ``--depth-max``, a config file, the API): one line naming the key.

- Every number in the config tree is finite (NaN and infinities are refused; no key's default is one).
- Every integer (counts, periods, ``seed``) is >= 0 and fits in 64 bits.
- ``clock.speed``, ``clock.updates_per_frame``, ``clock.offline_updates``, ``seed`` and ``depth_max`` lie in the
  range of the run-options table (:mod:`.run.option_table`), as ``--speed`` etc. do.
- The keys in :data:`POSITIVE` are > 0 (``max_gaussians=-5`` would map nothing and report it as a result).
- ``sh_degree`` is 0..3, ``background`` three numbers in [0, 1].
- ``supervision.mode`` is one of auto / area / point, with ``supervision.pairs`` and ``band_px`` >= 1.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

POSITIVE = ("max_gaussians", "depth_max", "depth_scale", "max_image_side", "supervision.pairs", "supervision.band_px")
ANY_INTEGER: tuple[str, ...] = ()  # none: numpy's generators take no negative seed
MAX_INTEGER = 2 ** 63 - 1  # torch and numpy take integers up to a signed 64-bit one


def _walk(obj, prefix: str = ""):
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _walk(v, prefix + f.name + ".")
        else:
            yield prefix + f.name, v


def check_values(cfg) -> None:
    """Raise ValueError naming the first key of ``cfg`` (a Config) whose value no run can use."""
    for key, v in _walk(cfg):
        items = v if isinstance(v, (tuple, list)) else (v,)
        for x in items:
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                continue
            if isinstance(x, float) and not math.isfinite(x):
                raise ValueError(f"config key {key}: {v!r} is not a finite number")
            if isinstance(x, int) and x < 0 and key not in ANY_INTEGER:
                raise ValueError(f"config key {key}: {v!r} is negative (must be >= 0)")
            if isinstance(x, int) and x > MAX_INTEGER:
                raise ValueError(f"config key {key}: {x} is too large (at most 2**63 - 1)")
        if key in POSITIVE and not (isinstance(v, (int, float)) and v > 0):
            raise ValueError(f"config key {key}: must be > 0, got {v!r}")
    from ..run.option_table import check_option

    for key, name in (("clock.speed", "speed"), ("clock.updates_per_frame", "updates_per_frame"),
                      ("seed", "seed"), ("depth_max", "depth_max"), ("clock.offline_updates", "offline_updates")):
        obj = cfg
        for part in key.split(".")[:-1]:
            obj = getattr(obj, part)
        value = getattr(obj, key.split(".")[-1], None)
        if value is not None:
            try:
                check_option(name, value, f"config key {key}")
            except ValueError as e:
                raise ValueError(str(e).replace(f"config key {key} ", f"config key {key}: ", 1)) from None
    if not (isinstance(cfg.sh_degree, int) and 0 <= cfg.sh_degree <= 3):
        raise ValueError(f"config key sh_degree: must be 0, 1, 2 or 3, got {cfg.sh_degree!r}")
    bg = cfg.background
    if not (isinstance(bg, (tuple, list)) and len(bg) == 3 and all(isinstance(x, (int, float)) and
                                                                  not isinstance(x, bool) and 0 <= x <= 1
                                                                  for x in bg)):
        raise ValueError(f"config key background: must be three numbers in [0, 1] (red, green, blue), got "
                         f"{list(bg) if isinstance(bg, (tuple, list)) else bg!r}")
    from ..scheduling.supervision import MODES

    if cfg.supervision.mode not in MODES:
        raise ValueError(f"config key supervision.mode: choose from {', '.join(MODES)}, got {cfg.supervision.mode!r}")
    from ..kernels import KERNEL_SETS

    if cfg.optim.kernels not in KERNEL_SETS:
        raise ValueError(f"config key optim.kernels: choose from {', '.join(KERNEL_SETS)}, got {cfg.optim.kernels!r}")


class ConfigError(ValueError):
    """A config file or dict that cannot be used: the message names the file and the key."""


def checked_value(default: Any, value: Any, where: str, key: str) -> Any:
    """``value`` for a key whose default is ``default``, of the default's type: an int key takes an integer (an
    integral float such as 3e5 too), a float key a number, a str key a string, a tuple key a list of values of
    its elements' type; a bool is neither an int nor a float here."""
    given = value

    def wrong(want: str):
        return ConfigError(f"{where}: {key} takes {want}, got {type(given).__name__} {given!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise wrong("true or false")
    elif isinstance(default, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong("an integer")
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise wrong("a number")
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise wrong("a string")
    elif isinstance(default, tuple):
        if not isinstance(value, (list, tuple)):
            raise wrong("a list")
        value = tuple(value)
        kinds = {type(x) for x in default}
        if kinds == {str} and not all(isinstance(x, str) for x in value):
            raise wrong("a list of strings")
        if kinds and kinds <= {int, float} and not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                     for x in value):
            raise wrong("a list of numbers")
    return value
