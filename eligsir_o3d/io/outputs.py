"""Checks a command makes on its output paths before it reads or computes anything, so that a bad output path
costs a second, not a run, and never an input.

- :func:`check_output`: the path can be written: a regular file, a new path in a folder (or one that can be
  made), a character device or a FIFO (written directly, never replaced: :mod:`.atomic`). A directory, a block
  device or socket, or a path below a file is refused with :class:`~.atomic.WriteFailed` (exit 3).
- :func:`check_output_folder`: a results folder path that exists as something other than a folder is refused the
  same way.
- :func:`check_export_outputs`: ``eligsir export``'s outputs: none may be the map or a file beside it that the
  export reads, nor each other (:func:`~.guards.refuse_overwriting_inputs`, exit 2), each suffix says its format,
  and each is writable.
"""

from __future__ import annotations

import errno
from pathlib import Path

from .atomic import WriteFailed, output_kind
from .inputs import printable


def check_output(path: str | Path, option: str) -> None:
    """Raise :class:`WriteFailed` when ``path`` (given as ``option``) cannot be an output file."""
    path = Path(path)
    kind = output_kind(path)
    if kind == "directory":
        raise WriteFailed(path, f"{option} names a directory; give a file path", errno.EISDIR)
    if kind == "other":
        raise WriteFailed(path, f"{option} names a block device or a socket; give a file path")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise WriteFailed(path, f"{option}: {printable(parent)} is a file, not a folder", errno.ENOTDIR)


def check_output_folder(path: str | Path, option: str) -> None:
    """Raise :class:`WriteFailed` when ``path`` exists and is not a folder (or lies below a file)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise WriteFailed(path, f"{option} names a file, not a folder; give a folder path", errno.ENOTDIR)
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise WriteFailed(path, f"{option}: {printable(parent)} is a file, not a folder", errno.ENOTDIR)


def check_export_outputs(map_ply: str | Path, poses: str | Path | None, **outputs) -> None:
    """``eligsir export``'s output options (``mesh``, ``point_cloud``, ``spz``, ``splat``, ``for_viewers``: path
    or None) checked before anything is read (see the module docstring)."""
    from ..export.geometry import CLOUD_SUFFIXES, MESH_SUFFIXES, check_geometry_path
    from ..export.web import check_web_path
    from .guards import refuse_overwriting_inputs

    map_ply = Path(map_ply)
    flags = {f"--{k.replace('_', '-')}": v for k, v in outputs.items()}
    beside = {name: map_ply.parent / name for name in ("trajectory.txt", "config.json", "run.json")}
    refuse_overwriting_inputs(flags, {"the map": map_ply, "--poses": poses, **beside})
    check_geometry_path(outputs.get("mesh"), "--mesh", MESH_SUFFIXES)
    check_geometry_path(outputs.get("point_cloud"), "--point-cloud", CLOUD_SUFFIXES)
    for fmt in ("spz", "splat"):
        if outputs.get(fmt) is not None:
            check_web_path(outputs[fmt], fmt)
    for flag, path in flags.items():
        if path is not None:
            check_output(path, flag)
