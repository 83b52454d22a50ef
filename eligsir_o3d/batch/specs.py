"""What a batch maps: one :class:`SequenceSpec` per sequence, from paths or manifest files, and the state of its
results folder (finished, resumable, new) recorded in ``<out>/<name>/batch.json``.

A manifest is a text file (``.txt``, ``.list`` or ``.manifest``) with one sequence a line, optionally followed by
that sequence's own options, which override the batch's::

    # name-less lines take the folder's name; relative paths are relative to the manifest's folder
    /data/tum/rgbd_dataset_freiburg1_desk --max-frames 300
    kitchen/                              --name kitchen-odo --pose odometry
    synthetic                             --max-frames 120 --config fast.json
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import os
import re
import shlex
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..io.atomic import atomic_write_text
from ..io.inputs import printable, read_json, read_text
from ..run.option_table import check_option, default
from .limits import RESERVED_NAMES

MANIFEST_SUFFIXES = (".txt", ".list", ".manifest")
STATE_FILE = "batch.json"


class BatchError(ValueError):
    """A batch that cannot start (bad manifest line, Ray missing, foreign results folder): one line, no traceback."""


@dataclass
class SequenceSpec:
    """One sequence of a batch and its options (None: the batch's default)."""

    path: str
    name: str | None = None
    max_frames: int | None = None
    pose: str | None = None
    speed: float | None = None
    config: str | None = None  # a config.json to start from
    updates_per_frame: int | None = None
    eval_every: int | None = None
    holdout_every: int | None = None
    seed: int | None = None
    cost_model: str | None = None  # calibrate | shipped | FILE (eligsir_o3d.run.options.COST_MODEL_RULE)
    where: str = ""  # "manifest.txt:3" for error messages


_OPTIONS = {  # manifest option -> (field, type)
    "--name": ("name", str), "--max-frames": ("max_frames", int), "--pose": ("pose", str),
    "--speed": ("speed", float), "--config": ("config", str), "--updates-per-frame": ("updates_per_frame", int),
    "--eval-every": ("eval_every", int), "--holdout-every": ("holdout_every", int), "--seed": ("seed", int),
    "--cost-model": ("cost_model", str),
}


class _LineParser(argparse.ArgumentParser):
    def error(self, message):  # argparse would print usage and exit
        raise BatchError(message)


def _line_parser() -> argparse.ArgumentParser:
    p = _LineParser(prog="manifest line", add_help=False, allow_abbrev=False)
    p.add_argument("path")
    for opt, (dest, tp) in _OPTIONS.items():
        p.add_argument(opt, dest=dest, type=tp, default=None)
    return p


def read_manifest(path: str | Path) -> list[SequenceSpec]:
    """The sequences listed in a manifest file (see the module docstring); errors name the file and line."""
    path = Path(path)
    try:
        text = read_text(path, "manifest")  # a regular file, size-capped
    except ValueError as e:
        raise BatchError(str(e)) from None
    parser, specs = _line_parser(), []
    for no, line in enumerate(text.splitlines(), 1):
        where = f"{path}:{no}"
        try:
            words = shlex.split(line, comments=True)  # quotes for paths with spaces, '#' starts a comment
            if not words:
                continue
            args = vars(parser.parse_args(words))
        except (BatchError, ValueError) as e:
            raise BatchError(f"{where}: {e}") from None
        seq = args.pop("path")
        if seq != "synthetic" and not os.path.isabs(seq):
            seq = str(path.parent / seq)
        if args.get("config") and not os.path.isabs(args["config"]):
            args["config"] = str(path.parent / args["config"])
        specs.append(SequenceSpec(path=seq, where=where, **args))
    if not specs:
        raise BatchError(f"{path}: the manifest lists no sequences")
    return specs


def expand_inputs(inputs) -> list[SequenceSpec]:
    """Paths, manifest files and :class:`SequenceSpec` objects -> specs with unique, folder-safe names."""
    specs: list[SequenceSpec] = []
    for item in inputs:
        if isinstance(item, SequenceSpec):
            specs.append(copy.copy(item))
        elif Path(str(item)).suffix.lower() in MANIFEST_SUFFIXES and Path(str(item)).is_file():
            specs.extend(read_manifest(item))
        else:
            specs.append(SequenceSpec(path=str(item), where=str(item)))
    if not specs:
        raise BatchError("no sequences given")
    bases = [re.sub(r"[^A-Za-z0-9._-]+", "_", s.name or Path(s.path.rstrip("/")).name or "sequence").strip("._")
             or "sequence" for s in specs]
    for k, (s, base) in enumerate(zip(specs, bases)):
        if base.lower() in RESERVED_NAMES:  # the batch folder's own files
            if s.name is not None:
                raise BatchError(f"{printable(s.where)}: --name {s.name!r} is the batch folder's own "
                                 f"{base}; choose another name")
            bases[k] = f"{base}-sequence"
    named: set[str] = set()
    for s, base in zip(specs, bases):
        if s.name is not None:
            if base in named:
                raise BatchError(f"{s.where}: the name {s.name!r} is used twice")
            named.add(base)
    for s, base in zip(specs, bases):
        if s.name is None:  # a name shared with another spec gets its own suffix, whatever the inputs' order
            s.name = base if bases.count(base) == 1 else f"{base}-{_spec_key(s)}"
        else:
            s.name = base
    if len({s.name for s in specs}) < len(specs):
        dup = next(s for s in specs if [t.name for t in specs].count(s.name) > 1)
        raise BatchError(f"{dup.where}: the sequence {dup.path!r} is listed twice with the same options")
    return specs


def _spec_key(spec: SequenceSpec) -> str:
    """Six hex digits of what a spec maps (its resolved path and options): the same spec, the same folder name."""
    fields = {k: v for k, v in dataclasses.asdict(spec).items() if k not in ("name", "where")}
    if fields["path"] != "synthetic":
        fields["path"] = str(Path(fields["path"]).resolve())
    return hashlib.sha1(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:6]


@dataclass
class Defaults:
    """Batch-wide options; a spec's own value wins where it has one."""

    max_frames: int | None = None
    pose: str = "gt"
    speed: float | None = None
    config: str | None = None
    updates_per_frame: int | None = None
    eval_every: int = default("eval_every")
    holdout_every: int = default("holdout_every")
    seed: int | None = None
    cost_model: str | None = None  # None: the config's (shipped by default), see COST_MODEL_RULE
    device: str | None = None
    checkpoint_every: int = default("checkpoint_every")
    plots: bool = True  # also the pictures (heldout/*.png, flythrough.mp4)
    extra_options: dict = field(default_factory=dict)  # any other RunOptions field, for the Python API


def build_request(spec: SequenceSpec, d: Defaults) -> dict:
    """Everything that decides a sequence's result, as plain JSON: the config dict and the run options.

    Two runs with equal requests (device and renderer aside) give the same map; a results folder is only reused
    (skipped when finished, resumed otherwise) for an equal request.
    """
    from ..run.options import MapOptions, to_config

    pick = lambda name: getattr(spec, name) if getattr(spec, name) is not None else getattr(d, name)  # noqa: E731
    cfg_path = pick("config")
    try:  # the run-options table: the same ranges and messages as eligsir map
        checked = {n: check_option(n, pick(n)) for n in ("max_frames", "speed", "updates_per_frame", "eval_every",
                                                         "holdout_every", "seed")}
        check_option("checkpoint_every", d.checkpoint_every)
    except ValueError as e:
        raise BatchError(f"{printable(spec.where)}: {e}") from None
    asked = MapOptions(config=cfg_path, seed=pick("seed"), updates_per_frame=pick("updates_per_frame"),
                       speed=pick("speed"), device=d.device, cost_model=pick("cost_model"))
    try:
        cfg = to_config(asked)  # the one options -> Config path of eligsir map
    except (OSError, ValueError, TypeError) as e:
        raise BatchError(f"{spec.where}: cannot read config {cfg_path}: {e}") from None
    path = spec.path if spec.path == "synthetic" else str(Path(spec.path).resolve())
    opts = dict(max_frames=checked["max_frames"], pose=pick("pose"), eval_every=checked["eval_every"],
                holdout_every=checked["holdout_every"], checkpoint_every=d.checkpoint_every, plots=d.plots,
                pictures=d.plots,
                **d.extra_options)
    return {"name": spec.name, "path": path, "options": opts, "config": cfg.to_dict()}


def _comparable(request: dict) -> dict:
    r = json.loads(json.dumps(request))  # a deep copy with JSON's types (tuples -> lists)
    for k in ("device", "renderer"):  # where it ran does not change what was asked for
        r["config"].pop(k, None)
    for k in ("plots", "pictures", "checkpoint_every"):
        r["options"].pop(k, None)
    return r


def read_state(folder: Path) -> dict | None:
    try:
        return read_json(folder / STATE_FILE, "batch state")
    except ValueError:
        return None


def write_state(folder: Path, state: dict) -> None:
    """Atomic replace, so that a killed worker never leaves a half-written state file."""
    atomic_write_text(folder / STATE_FILE, json.dumps(state, indent=1))


def folder_status(folder: Path, request: dict) -> str:
    """'new' (nothing there), 'done' (finished for this request), 'resume' (unfinished run of this request),
    'changed' (our folder, another request) or 'foreign' (files not written by a batch)."""
    if not folder.exists() or not any(folder.iterdir()):
        return "new"
    state = read_state(folder)
    if state is None:
        return "foreign"
    if _comparable(state.get("request", {})) != _comparable(request):
        return "changed"
    if state.get("state") == "done" and (folder / "metrics.json").is_file():
        return "done"
    return "resume"


def start_state(folder: Path, request: dict) -> dict:
    """The state a task writes when it starts (or restarts) mapping ``request`` into ``folder``."""
    old = read_state(folder) or {}
    same = old and _comparable(old.get("request", {})) == _comparable(request)
    return {"request": request, "state": "running", "attempts": (old.get("attempts", 0) if same else 0) + 1,
            "pid": os.getpid(), "host": os.uname().nodename, "started": time.time()}


def spec_dict(spec: SequenceSpec) -> dict:
    return asdict(spec)
