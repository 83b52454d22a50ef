"""Image dimensions from the file header, read before anything is decoded: a 3 MB PNG can
declare 40000x40000 16-bit pixels (3.2 GB decoded), so a reader checks the declared size first.

- :func:`image_size`: (width, height) of a PNG (its IHDR chunk) or a baseline/progressive JPEG (its SOF segment),
  reading at most a few kilobytes; None for another format or a header that cannot be parsed (the decoder then
  says what is wrong with the file).
- :func:`check_declared_size`: refuses a file whose declared size exceeds :data:`LIMITS` ``["max_image_side"]``
  (the config key ``max_image_side``, set by the pipeline) or differs from the camera's.
"""

from __future__ import annotations

import struct
from pathlib import Path

LIMITS = {"max_image_side": 16384}  # pixels, either side; the pipeline sets it from Config.max_image_side
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
MAX_HEADER_BYTES = 1 << 20  # a JPEG's SOF comes after its APP segments (EXIF thumbnails): read at most 1 MiB


def set_max_image_side(side: int) -> None:
    LIMITS["max_image_side"] = int(side)


def _png_size(head: bytes) -> tuple[int, int] | None:
    if len(head) < 24 or head[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


def _jpeg_size(f) -> tuple[int, int] | None:
    f.seek(2)
    read = 2
    while read < MAX_HEADER_BYTES:
        b = f.read(1)
        if not b:
            return None
        if b != b"\xff":
            continue  # not at a marker: resynchronise
        marker = f.read(1)
        while marker == b"\xff":  # fill bytes
            marker = f.read(1)
        if not marker:
            return None
        m = marker[0]
        if m in (0xD8, 0x01) or 0xD0 <= m <= 0xD7:  # markers without a length
            continue
        if m == 0xD9:  # end of image before any frame header
            return None
        seg = f.read(2)
        if len(seg) < 2:
            return None
        length = struct.unpack(">H", seg)[0]
        if m in _SOF:
            body = f.read(5)
            if len(body) < 5:
                return None
            h, w = struct.unpack(">HH", body[1:5])
            return int(w), int(h)
        f.seek(length - 2, 1)
        read = f.tell()
    return None


def image_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) the PNG or JPEG file at ``path`` declares, or None (another format, no parsable header)."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head.startswith(PNG_SIGNATURE):
            return _png_size(head)
        if head[:2] == b"\xff\xd8":
            return _jpeg_size(f)
    return None


def check_declared_size(path: Path, index: int, what: str, expected: tuple[int, int] | None = None) -> None:
    """Raise ValueError (a DatasetError when given by the caller) before decoding ``path`` when its header declares
    more than ``max_image_side`` pixels a side, or another size than ``expected`` (width, height)."""
    from .errors import DatasetError

    try:
        size = image_size(path)
    except OSError as e:
        raise DatasetError(f"frame {index}: cannot read {what} file {path}: {e}") from None
    if size is None:
        return
    w, h = size
    limit = LIMITS["max_image_side"]
    if w > limit or h > limit or w == 0 or h == 0:
        raise DatasetError(f"frame {index}: {what} file {path} declares {w}x{h} pixels, beyond the "
                           f"{limit}-pixel limit (config key max_image_side); not decoded")
    if expected is not None and (w, h) != tuple(expected):
        raise DatasetError(f"frame {index}: {what} file {path} is {w}x{h} but the intrinsics are for "
                           f"{expected[0]}x{expected[1]}")
