"""Checkpoint files: encoding a mapper state compactly and writing it atomically, so that a run killed at any moment
resumes. What the state holds is the Reconstructor's business (``Reconstructor.state_dict``/``load_state_dict``);
this module only encodes and writes what it is handed, and reads it back.

    rec.save("runs/kitchen/checkpoint.pt")                        # = save_checkpoint(rec.state_dict(), path)
    rec = Reconstructor.load("runs/kitchen/checkpoint.pt")        # after a crash: same map, same policies
    read_checkpoint(path)["extra"]                                # a driver's own progress, saved beside it

Retained views are stored once each, compactly and losslessly: colour as uint8 (or uint16) when that reproduces
the float colour bit for bit (always so for 8-bit sources), depth as uint16 at the config's ``depth_scale`` when
that reproduces it bit for bit (16-bit PNG depth), float32 otherwise. With ``sequence=`` a view that is frame
``i`` of the sequence is stored as a reference (index, pose, timestamp, checksum) and re-read from the sequence
on load. A policy state may hold a view's image tensors or the Frame itself; either is replaced by a reference
to the one stored copy.

The file is a ``torch.save`` archive loaded with ``weights_only=True`` (plain containers, numbers, strings and
tensors only: loading a checkpoint cannot run code). It is written to a temporary file in the same folder,
flushed and fsynced, then renamed over the previous checkpoint (``os.replace`` is atomic), so a crash or a
SIGKILL in the middle of a write leaves the previous checkpoint intact and loadable.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .atomic import atomic_write
from ..core.camera import Camera
from ..core.frame import DEPTH_MAX, Frame

FORMAT = "eligsir-checkpoint"
VERSION = 1
MIN_VERSION = 1  # the oldest format this version reads (no conversion from older ones)


class CheckpointError(ValueError):
    """A checkpoint that cannot be written or read (names the file and what is wrong)."""


# ---- save --------------------------------------------------------------------------------------------------
def save_checkpoint(state, path: str | Path, *, extra: dict | None = None, sequence=None) -> Path:
    """Write a mapper state to ``path`` (atomic replace). Returns the path.

    state: ``Reconstructor.state_dict()`` (or a Reconstructor, whose ``state_dict()`` is taken); its ``config``
    gives the depth scale and range the views are encoded with. extra: a caller's dict of plain values/tensors,
    handed back as ``read_checkpoint(path)["extra"]``. sequence: the RGBDSequence the views came from; views that
    are unchanged frames of it are stored as references instead of images (the same sequence must then be given
    to :func:`read_checkpoint`).
    """
    if not isinstance(state, dict):
        state = state.state_dict()
    path = Path(path)
    cfg = state.get("config", {})
    frames = _FrameTable(float(cfg.get("depth_scale", 1000.0)), sequence, float(cfg.get("depth_max", DEPTH_MAX)))
    payload = {"format": FORMAT, "version": VERSION, "saved_at": time.time(), **state, "extra": extra}
    packed = _pack(payload, frames, "checkpoint")
    packed["frames"] = frames.encoded()
    _atomic_write(path, packed)
    return path


def _serialize(payload: dict, f) -> None:
    """Write ``payload`` to the open binary file ``f`` (a seam for the crash-mid-write test)."""
    torch.save(payload, f)


def _atomic_write(path: Path, payload: dict) -> None:
    """Temporary file in the same folder, fsync, ``os.replace`` (:func:`.atomic_io.atomic_write`): a failed write
    (full disk, I/O error) raises :class:`~.atomic_io.WriteFailed` and leaves the previous checkpoint intact."""
    atomic_write(path, lambda f: _serialize(payload, f))


# ---- load --------------------------------------------------------------------------------------------------
def read_checkpoint(path: str | Path, *, sequence=None) -> dict:
    """The decoded payload of a checkpoint: the state (config dict, stats, policy states ...) and ``extra``, for
    ``Reconstructor.from_checkpoint``. Views saved as sequence references decode to None unless ``sequence`` is
    given.
    Raises :class:`CheckpointError` for a missing, truncated, corrupt or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # zip/pickle errors of a truncated or foreign file
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt?): "
                              f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an eligsir_o3d checkpoint")
    try:
        version = int(raw.get("version", 0))
    except (TypeError, ValueError):
        raise CheckpointError(f"{path}: checkpoint version {raw.get('version')!r} is not a number") from None
    if version > VERSION:
        raise CheckpointError(f"{path}: checkpoint version {version} is newer than this eligsir_o3d reads "
                              f"({VERSION}); upgrade the package")
    if version < MIN_VERSION:
        readable = f"{MIN_VERSION}" if MIN_VERSION == VERSION else f"{MIN_VERSION}-{VERSION}"
        raise CheckpointError(f"{path}: checkpoint version {version} is older than this eligsir_o3d reads "
                              f"({readable}); map the sequence again (no conversion from older ones)")
    cfg = raw.get("config", {})
    frames = _decode_frames(raw.get("frames", []), path, sequence, float(cfg.get("depth_max", DEPTH_MAX)))
    out = _unpack({k: v for k, v in raw.items() if k != "frames"}, frames)
    out["path"] = str(path)
    out["unresolved_views"] = sum(f is None for f in frames)
    return out


# ---- retained views, stored once each ----------------------------------------------------------------------
class _FrameTable:
    """The distinct Frames met while packing, encoded compactly or as sequence references."""

    def __init__(self, depth_scale: float, sequence, depth_max: float):
        self.depth_scale, self.sequence, self.depth_max = float(depth_scale), sequence, float(depth_max)
        self.frames: list[Frame] = []
        self._by_id: dict[int, int] = {}  # id(frame) -> k
        self._tensors: dict[int, tuple[int, str]] = {}  # id(tensor) -> (k, "color" | "depth")

    def add(self, frame: Frame) -> int:
        k = self._by_id.get(id(frame))
        if k is None:
            k = len(self.frames)
            self.frames.append(frame)
            self._by_id[id(frame)] = k
            self._tensors[id(frame.color)] = (k, "color")
            self._tensors[id(frame.depth)] = (k, "depth")
        return k

    def tensor_ref(self, t: torch.Tensor) -> tuple[int, str] | None:
        return self._tensors.get(id(t))

    def encoded(self) -> list[dict]:
        return [self._encode(f) for f in self.frames]

    def _encode(self, f: Frame) -> dict:
        head = {"camera": dataclasses.asdict(f.camera), "T_world_cam": torch.from_numpy(np.array(f.T_world_cam)),
                "timestamp": float(f.timestamp), "index": int(f.index),
                "checksum": _checksum(f.color, f.depth)}
        if self.sequence is not None and self._matches_sequence(f, head["checksum"]):
            return {**head, "ref": "sequence"}
        return {**head, "color": _encode_color(f.color), "depth": _encode_depth(f.depth, self.depth_scale)}

    def _matches_sequence(self, f: Frame, checksum: str) -> bool:
        """Whether frame ``f.index`` of the sequence, read again, is this view (checked once per view: a view's
        images do not change, and re-reading every retained view at every checkpoint costs seconds)."""
        key = (id(f), id(self.sequence), self.depth_max)
        hit = _VERIFIED.get(key)
        if hit is not None and hit[0]() is f and hit[1] == checksum:
            return True
        if not 0 <= f.index < len(self.sequence):
            return False
        try:
            g = self.sequence.frame(f.index, depth_max=self.depth_max, T_world_cam=f.T_world_cam)
        except (ValueError, OSError):
            return False
        same = g.color.shape == f.color.shape and _checksum(g.color, g.depth) == checksum
        if same:
            for k in [k for k, v in _VERIFIED.items() if v[0]() is None]:  # forget evicted views
                del _VERIFIED[k]
            _VERIFIED[key] = (weakref.ref(f), checksum)
        return same


_VERIFIED: dict[tuple, tuple[weakref.ref, str]] = {}  # views known to equal their sequence frame


def _checksum(color: torch.Tensor, depth: torch.Tensor) -> str:
    """Bit-exact fingerprint of a view's images (BLAKE2b of the raw float32 bytes, ~5 ms at 640x480)."""
    h = hashlib.blake2b(digest_size=16)
    for t in (color, depth):
        h.update(np.ascontiguousarray(t.detach().cpu().numpy()).tobytes())
    return h.hexdigest()


def _encode_color(c: torch.Tensor) -> dict:
    c = c.detach().cpu()
    for dtype, top in ((np.uint8, 255.0), (np.uint16, 65535.0)):
        q = np.clip(np.round(c.numpy().astype(np.float64) * top), 0, top).astype(dtype)
        e = {"q": torch.from_numpy(q), "top": top}
        if torch.equal(_decode_color(e), c):  # bit-exact, or not at all
            return e
    return {"raw": c.clone()}


def _encode_depth(d: torch.Tensor, depth_scale: float) -> dict:
    d = d.detach().cpu()
    q = np.round(d.numpy().astype(np.float64) * depth_scale)
    if q.size and q.min() >= 0 and q.max() <= 65535:
        e = {"q": torch.from_numpy(q.astype(np.uint16)), "scale": float(depth_scale)}
        if torch.equal(_decode_depth(e), d):  # bit-exact, or not at all
            return e
    return {"raw": d.clone()}


def _decode_color(e: dict) -> torch.Tensor:
    if "raw" in e:
        return e["raw"].float()
    return torch.from_numpy(e["q"].numpy().astype(np.float32) / e["top"])  # as Frame.from_arrays


def _decode_depth(e: dict) -> torch.Tensor:
    if "raw" in e:
        return e["raw"].float()
    return torch.from_numpy(e["q"].numpy().astype(np.float32) / float(e["scale"]))  # as Frame.from_arrays


def _decode_frames(entries: list, path: Path, sequence, depth_max: float) -> list[Frame | None]:
    frames = []
    for e in entries:
        cam = Camera(**e["camera"])
        T = e["T_world_cam"].numpy().astype(np.float64)
        if e.get("ref") == "sequence":
            if sequence is None:
                frames.append(None)
                continue
            try:
                f = sequence.frame(int(e["index"]), depth_max=depth_max, T_world_cam=T)
            except (ValueError, OSError) as err:
                raise CheckpointError(f"{path}: cannot re-read retained view {e['index']} from the sequence: "
                                      f"{err}") from None
            if _checksum(f.color, f.depth) != e["checksum"]:
                raise CheckpointError(f"{path}: frame {e['index']} of the sequence differs from the retained view "
                                      f"that was checkpointed (a different sequence or depth_max?)")
            color, depth = f.color, f.depth
        else:
            color, depth = _decode_color(e["color"]), _decode_depth(e["depth"])
        frames.append(Frame(color, depth, cam, T, float(e["timestamp"]), int(e["index"])))
    return frames


# ---- packing: only what torch.load(weights_only=True) reads back -------------------------------------------
_PLAIN = (str, int, float, bool, type(None), torch.dtype, torch.device, torch.Size)


def _pack(obj: Any, frames: _FrameTable, where: str) -> Any:
    if isinstance(obj, torch.Tensor):
        ref = frames.tensor_ref(obj)
        if ref is not None:
            return {"__view_tensor__": ref[0], "field": ref[1]}
        t = obj.detach().cpu()
        if t.untyped_storage().nbytes() != t.numel() * t.element_size():
            t = t.clone()  # a slice would drag its whole storage into the file
        return t
    if isinstance(obj, _PLAIN):
        return obj
    if isinstance(obj, Frame):
        return {"__frame__": frames.add(obj)}
    if isinstance(obj, Camera):
        return {"__camera__": dataclasses.asdict(obj)}
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": torch.from_numpy(np.ascontiguousarray(obj).copy())}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        for k in obj:
            if not isinstance(k, (str, int, float, bool)):
                raise CheckpointError(f"cannot checkpoint {where}: key {k!r} of type {type(k).__name__}")
        return {k: _pack(v, frames, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, tuple):
        return {"__tuple__": [_pack(v, frames, f"{where}[{i}]") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_pack(v, frames, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise CheckpointError(f"cannot checkpoint {where}: a {type(obj).__module__}.{type(obj).__name__} (state_dict() "
                          f"must hold only containers, numbers, strings, tensors, numpy arrays, Frames and Cameras)")


def _unpack(obj: Any, frames: list[Frame]) -> Any:
    if isinstance(obj, dict):
        if "__view_tensor__" in obj:
            f = frames[obj["__view_tensor__"]]
            return None if f is None else f.color if obj["field"] == "color" else f.depth
        if "__frame__" in obj:
            return frames[obj["__frame__"]]
        if "__camera__" in obj:
            return Camera(**obj["__camera__"])
        if "__ndarray__" in obj:
            return obj["__ndarray__"].numpy()
        if "__tuple__" in obj:
            return tuple(_unpack(v, frames) for v in obj["__tuple__"])
        return {k: _unpack(v, frames) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_unpack(v, frames) for v in obj]
    return obj
