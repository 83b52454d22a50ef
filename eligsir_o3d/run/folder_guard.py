"""A results folder holds one run's results, never two mixed.

- A folder that holds another run's results (any of :data:`RESULT_FILES`) is refused unless the run is given
  ``overwrite`` (``eligsir map --overwrite``) or ``resume`` with a checkpoint there (``--resume``; the checkpoint
  itself then checks that it is of this sequence, config and split, :mod:`.resume`).
- ``--resume`` where the folder holds results but no ``checkpoint.pt`` (a finished run, maybe of another sequence)
  is refused: there is nothing to continue, and mapping from scratch would overwrite it. An empty or new folder
  starts from frame 0 (a batch retry of an attempt that died before its first checkpoint).
- On overwrite, every file an earlier ``eligsir map`` wrote there and the new run did not write again is removed once
  the new run has written its results, so what the new run does not write (``heldout/*.png`` and ``flythrough.mp4``
  under ``--no-pictures``, plots under ``--no-plots``, a stale checkpoint) cannot sit beside the new map. Until then
  the earlier files stay: a run that fails (a full disk, Ctrl-C) leaves every earlier file as it was, and the files
  it does write replace theirs atomically. Files eligsir does not write are left alone.
- :func:`fresh_folder`: the folder a run without ``--out`` takes: ``runs/map``, else ``runs/map-2``, ``-3``, ...

Refusals are :class:`FolderInUse` (a ``ValueError``: one line, exit 2).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

log = logging.getLogger("eligsir_o3d")

# what eligsir map writes in its folder (results.py, visual/run_pictures.py, eval/plots.py, the pipeline)
RESULT_FILES = ("metrics.json", "map.ply", "run.json", "config.json", "trajectory.txt", "trajectory_refined.txt",
                "checkpoint.pt", "cells.json", "fidelity_trace.csv", "flythrough.mp4", "trajectory_topview.png",
                "heldout_quality_vs_time.png", "heldout_quality_vs_progress.png", "heldout_quality_vs_mpix.png",
                "cuc20_vs_progress.png", "cell_psnr_topdown.png")
RESULT_DIRS = ("heldout",)
MARKERS = ("metrics.json", "map.ply", "run.json", "checkpoint.pt")  # a folder with one of these holds a run


class FolderInUse(ValueError):
    """The results folder holds another run's results (the message says what to pass)."""

    exit_code = 2


def held_results(folder: str | Path) -> list[str]:
    """The names of the run markers in ``folder`` (empty: no run's results there)."""
    folder = Path(folder)
    return [m for m in MARKERS if (folder / m).is_file() or (folder / m).is_symlink()]


def check_folder(folder: str | Path, resume: bool, overwrite: bool) -> dict:
    """Refuse (:class:`FolderInUse`) ``folder`` for a new run, per the module docstring; returns the earlier run's
    files (path -> modification time) that :func:`clear_stale` removes after the new run unless it rewrote them."""
    folder = Path(folder)
    found = held_results(folder)
    if not found:
        return {}
    if resume:
        if (folder / "checkpoint.pt").is_file():
            return {}  # the checkpoint decides (sequence, config, split)
        if not overwrite:
            raise FolderInUse(f"--resume: {folder} has no checkpoint.pt to continue (it holds the results of a "
                              f"finished run: {', '.join(found)}); map into a new --out, or pass --overwrite to "
                              f"replace them")
    elif not overwrite:
        raise FolderInUse(f"{folder} already holds the results of another run ({', '.join(found)}); pass --overwrite "
                          f"to replace them, --resume to continue an interrupted run, or choose another --out")
    return earlier_results(folder)


def earlier_results(folder: Path) -> dict:
    """What an earlier eligsir map wrote in ``folder``: path -> its modification time (links as links)."""
    paths = [folder / name for name in RESULT_FILES]
    for name in RESULT_DIRS:
        d = folder / name
        if d.is_dir() and not d.is_symlink():  # only the pictures eligsir wrote; a user's own files stay
            paths += [f for f in d.iterdir() if f.name in _pictures_written(folder, name)]
        paths.append(d)
    return {p: p.lstat().st_mtime_ns for p in paths if p.is_symlink() or p.is_file()
            or (p.name in RESULT_DIRS and p.is_dir())}


def _pictures_written(folder: Path, name: str) -> set[str]:
    """The names in ``folder/name`` that the earlier run lists as its pictures (metrics.json's ``pictures``), each
    of the form eligsir writes (``NNNNNN.png``); without a list (an older or unreadable metrics.json), every name
    of that form."""
    from ..io.inputs import read_json

    form = re.compile(r"^\d{6}\.png$")
    try:
        metrics = read_json(folder / "metrics.json", "metrics")
    except ValueError:
        metrics = None
    if isinstance(metrics, dict) and "pictures" in metrics:
        pictures = metrics.get("pictures") or {}
        listed = pictures.get(name) if isinstance(pictures, dict) else None
        names = {Path(p).name for p in listed or () if isinstance(p, str) and Path(p).parent.name == name}
    else:
        d = folder / name
        names = {f.name for f in d.iterdir()} if d.is_dir() else set()
    return {n for n in names if form.match(n)}


def clear_stale(earlier: dict) -> list[str]:
    """Remove the files of ``earlier`` (:func:`earlier_results`) that the new run did not write again (same
    modification time; links are removed, not followed) and the picture folder if that leaves it empty."""
    removed = []
    for p, mtime in earlier.items():
        if p.is_symlink() or p.is_file():
            if p.lstat().st_mtime_ns == mtime:
                p.unlink()
                removed.append(p.name)
    for p in earlier:
        if p.name in RESULT_DIRS and p.is_dir() and not p.is_symlink():
            try:
                p.rmdir()  # only when empty
                removed.append(p.name + "/")
            except OSError:
                pass
    if removed:
        log.warning("--overwrite: removed the earlier run's %s (not written by this run)", ", ".join(removed))
    return removed


def fresh_folder(base: str | Path = "runs/map") -> Path:
    """``base`` if it holds no run, else the first of ``base-2``, ``base-3``, ... that does not exist or is empty."""
    base = Path(base)

    def free(p: Path) -> bool:
        return not p.exists() and not p.is_symlink() or (p.is_dir() and not any(p.iterdir()))

    if free(base):
        return base
    n = 2
    while not free(base.with_name(f"{base.name}-{n}")):
        n += 1
    return base.with_name(f"{base.name}-{n}")
