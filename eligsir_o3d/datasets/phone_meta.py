"""Typed schemas of the phone captures' metadata: every field checked for type, finiteness and range before a
reader uses it, and a refusal is one line naming the file and the field.

- :class:`Record3DMeta`: a Record3D ``metadata`` (``.r3d``) / ``metadata.json`` (EXR + JPG export).
- :class:`PolycamCamera`: one Polycam ``keyframes/cameras/<stamp>.json``.
- :class:`OdometryRow`: one row of a Stray Scanner ``odometry.csv``.
- :func:`usable_stamps`: which frames' timestamps are finite and increasing; the others are skipped and reported.

Malformed poses are not refused here: a frame without a usable pose is left out and reported by its reader, as a
phone marks lost tracking.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..io.inputs import printable
from .base import DatasetError

MAX_SIDE = 16384  # pixels of an image side a phone capture may declare
MAX_FRAMES = 10_000_000  # frame numbers a capture may declare

Side = Annotated[int, Field(gt=0, le=MAX_SIDE, strict=True)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Rate = Annotated[float, Field(gt=0, le=10_000, allow_inf_nan=False)]  # frames per second


class _Schema(BaseModel):
    model_config = ConfigDict(extra="allow", frozen=True)


class Record3DMeta(_Schema):
    """Record3D's metadata: colour size ``w`` x ``h`` (px), column-major ``K`` (9 numbers), optional depth size
    ``dw`` x ``dh`` (px), ``fps`` (frames per second), ``poses`` (one entry a frame), ``frameTimestamps`` (s) and
    ``perFrameIntrinsicCoeffs``."""

    w: Side
    h: Side
    K: Annotated[list[Finite], Field(min_length=9, max_length=9)]
    poses: list[Any]
    dw: Optional[Side] = None
    dh: Optional[Side] = None
    fps: Optional[Rate] = None
    frameTimestamps: Optional[list[Any]] = None
    perFrameIntrinsicCoeffs: Optional[list[Any]] = None


class PolycamCamera(_Schema):
    """A Polycam keyframe camera: image ``width`` x ``height`` (px), ``fx``, ``fy``, ``cx``, ``cy`` (px), the pose
    fields ``t_00`` .. ``t_23`` (checked by the reader: a malformed pose leaves the frame out) and an optional
    ``timestamp``."""

    width: Side
    height: Side
    fx: Positive
    fy: Positive
    cx: Finite
    cy: Finite
    timestamp: Optional[Finite] = None


class OdometryRow(_Schema):
    """A Stray Scanner odometry row: position ``x``, ``y``, ``z`` (m), quaternion ``qx`` .. ``qw`` (a non-finite one
    marks lost tracking), an optional ``frame`` number and ``timestamp`` (s, checked by :func:`usable_stamps`)."""

    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float
    frame: Optional[Annotated[float, Field(ge=0, le=MAX_FRAMES, allow_inf_nan=False)]] = None
    timestamp: Optional[float] = None


def validated(schema: type[BaseModel], data: Any, where: str):
    """``schema`` validated from ``data``, or a :class:`DatasetError` naming ``where`` (the file, and line) and the
    first field at fault."""
    if not isinstance(data, dict):
        raise DatasetError(f"{printable(where)}: expected a JSON object of fields, got {type(data).__name__}")
    try:
        return schema.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "(the document)"
        got = printable(repr(err.get("input")))[:60]
        raise DatasetError(f"{printable(where)}: field {field!r}: {err['msg']} (got {got})") from None


def usable_stamps(stamps: list, names: list[str]) -> tuple[list[bool], list[str]]:
    """(usable, reports) of timestamps ``stamps`` (seconds) of the frames ``names``: a frame whose stamp is not a
    finite number, or not later than the last usable one, is unusable and reported as left out."""
    ok, reports, last = [], [], -math.inf
    for t, name in zip(stamps, names):
        good = isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t > last
        if good:
            last = t
        else:
            what = "not a finite number" if not (isinstance(t, (int, float)) and math.isfinite(t)) else \
                "not later than the frame before"
            reports.append(f"{printable(name)}: timestamp {printable(t)!s:.40} is {what}, left out")
        ok.append(good)
    return ok, reports
