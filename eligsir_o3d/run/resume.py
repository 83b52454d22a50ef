"""``--resume`` continues a results folder only with what made it: the same sequence, the same map-changing
settings and the same held-out split. Anything else would mix two runs in one map and one curve, so it is refused
with a message naming what differs:

    --resume: runs/x was made with optim.lrs.means=0.0005 (now 0.001); resume with the same settings or map
    into a new --out

The sequence is checked by the checkpoint itself (every retained view is re-read and its checksum compared,
:mod:`.checkpoint`). Here: the resolved config the checkpoint was taken with (it is also the config the resumed
mapper uses) against the resolved config of the new command, and the run's own record saved beside it
(``extra["run"]``: the held-out frame indices, the pose source, the offline reference).

Compared: every config key, except the ones that say where or how a run executes, not what map it makes:

- ``device``: a checkpoint is portable (``Reconstructor.from_checkpoint`` loads it on the new device and re-chooses
  the renderer there); ``renderer`` is compared only when the device type is the same.
- ``clock.on_bad_frame``: what to do with an unreadable frame from now on; the new value is applied.
- ``clock.cost`` / ``clock.cost_source`` when the new command asks to calibrate (``eligsir map``'s default): the
  run keeps the cost model fitted when it started, so its budget does not change half-way; an explicit model
  (``--cost-model shipped|FILE``) is compared. Likewise ``clock.cost_feedback``, which the calibration sets when
  the user left it at 0: only a value the user chose is compared.

Run options that are output only (``--checkpoint-every``, ``--eval-every``, ``--no-pictures``, plots, ``--quiet``)
are not recorded and may change; ``--refine`` acts after the stream, so it may change too.
"""

from __future__ import annotations

import json
from pathlib import Path

NOT_COMPARED = ("device", "clock.on_bad_frame", "max_image_side")  # max_image_side: a reading guard, not the map
APPLIED = ("clock.on_bad_frame",)  # taken from the new command when resuming


class ResumeMismatch(ValueError):
    """``--resume`` of a results folder that another sequence, config or split made (the message says which)."""


def run_record(held: list[int], pose: str, offline_reference: bool) -> dict:
    """What the pipeline saves beside each checkpoint (``extra["run"]``) and compares on resume."""
    return {"heldout": [int(i) for i in held], "pose": str(pose), "offline_reference": bool(offline_reference)}


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _norm(d: dict) -> dict:
    return _flat(json.loads(json.dumps(d)))  # tuples -> lists, as written to config.json


def config_differences(saved: dict, now: dict) -> list[tuple[str, object, object]]:
    """(key, saved value, new value) of the map-changing settings that differ between two ``Config.to_dict()``."""
    import torch

    a, b = _norm(saved), _norm(now)
    skip = set(NOT_COMPARED)
    if torch.device(str(a.get("device", "cpu"))).type != torch.device(str(b.get("device", "cpu"))).type:
        skip.add("renderer")
    if b.get("clock.cost_source") == "calibrate":
        skip |= {k for k in set(a) | set(b) if k == "clock.cost_source" or k.startswith("clock.cost.")}
        if b.get("clock.cost_feedback") == 0:  # not chosen: the calibration derives it (cost_source.CALIBRATED_FEEDBACK)
            skip.add("clock.cost_feedback")
    return [(k, a.get(k, "(absent)"), b.get(k, "(absent)")) for k in sorted(set(a) | set(b))
            if k not in skip and a.get(k) != b.get(k)]


def _indices(idx: list[int]) -> str:
    return ", ".join(map(str, idx[:6])) + (", ..." if len(idx) > 6 else "") if idx else "none"


def check_resume(out: str | Path, ck: dict, config, record: dict) -> None:
    """Raise :class:`ResumeMismatch` when checkpoint ``ck`` (``read_checkpoint``'s dict) of results folder ``out``
    was made with other settings than ``config`` (the new command's resolved Config) and ``record``
    (:func:`run_record` of the new command). A checkpoint written before these were recorded is not checked."""
    where = f"--resume: {out} was made with"
    fix = "resume with the same settings, or map into a new --out"
    diffs = config_differences(ck.get("config") or {}, config.to_dict())
    if diffs:
        said = ", ".join(f"{k}={v!r} (now {w!r})" for k, v, w in diffs[:4])
        more = f" and {len(diffs) - 4} more setting(s)" if len(diffs) > 4 else ""
        raise ResumeMismatch(f"{where} {said}{more}; {fix}")
    saved = (ck.get("extra") or {}).get("run")
    if not isinstance(saved, dict):
        return
    old, new = [int(i) for i in saved.get("heldout", [])], record["heldout"]
    if old != new:
        only_then, only_now = sorted(set(old) - set(new)), sorted(set(new) - set(old))
        raise ResumeMismatch(f"{where} a different held-out split: {len(old)} held-out frames then, {len(new)} now "
                             f"(held out only then: {_indices(only_then)}; only now: {_indices(only_now)}); "
                             f"use the same --holdout-every / --holdout-list / --max-frames, or map into a new --out")
    for key, flag in (("pose", "--pose"), ("offline_reference", "--offline-reference")):
        if key in saved and saved[key] != record[key]:
            raise ResumeMismatch(f"{where} {flag} {saved[key]!r} (now {record[key]!r}); {fix}")


def apply_new_settings(resumed, config) -> None:
    """Give the resumed Config ``resumed`` the :data:`APPLIED` settings of the new command's ``config``."""
    for key in APPLIED:
        *path, name = key.split(".")
        src, dst = config, resumed
        for p in path:
            src, dst = getattr(src, p), getattr(dst, p)
        setattr(dst, name, getattr(src, name))
