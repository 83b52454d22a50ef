"""The one way to read an input file: regular files only, a size cap before anything is read, decompression bounded
by a cap on what it produces, and one-line errors naming the file.

- :func:`read_bytes` / :func:`read_text` / :func:`read_json`: a path that is not a regular file (a directory, a
  FIFO, ``/dev/zero``, a socket, a symbolic link that loops or dangles) is refused before it is opened for reading;
  a file larger than ``max_bytes`` is refused from its size, and at most ``max_bytes + 1`` bytes are ever read (a
  file that grows while read is refused too). JSON nested deeper than :data:`MAX_JSON_DEPTH` is refused.
- :func:`read_zip_member`: a ZIP member whose declared size exceeds the cap is refused before it is inflated, and
  inflation stops at the cap whatever the header declares.
- :func:`lzfse_decompress`: LZFSE blocks' declared output sizes are summed from their headers before decoding.

Errors are :class:`InputRefused` (a ``ValueError``: one line, exit 2), or the ``error`` class a caller passes
(readers pass their ``DatasetError``). Names in messages are made printable (:func:`printable`).
"""

from __future__ import annotations

import errno as _errno
import json
import os
import stat
import struct
import zlib
from pathlib import Path

MIB = 2 ** 20
MAX_TEXT_BYTES = 64 * MIB  # configs, metadata, manifests, trajectories, CSV and index lists
MAX_JSON_DEPTH = 64  # nesting levels of a JSON document (a config is 3 deep, phone metadata 3)
MAX_BLOB_BYTES = 512 * MIB  # one decompressed frame blob (a 4K float32 depth image is 32 MiB)


class InputRefused(ValueError):
    """An input file that cannot be read safely; ``str()`` is one line naming the file and the reason."""


def printable(text: object) -> str:
    """``text`` with control characters (newline, carriage return, escape, ...) written as escapes, so a file or
    frame name can never start a line of its own or recolour a terminal."""
    s = str(text)
    if s.isprintable():
        return s
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in s)


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str | Path, what: str = "file", error: type = InputRefused) -> os.stat_result:
    """The ``os.stat`` of ``path`` (links followed) when it is a regular file; else ``error`` naming it."""
    name = printable(path)
    try:
        st = os.stat(path)
    except OSError as e:
        if e.errno == _errno.ELOOP:
            raise error(f"{name}: {what} is a symbolic link that loops (it points back at itself)") from None
        if e.errno == _errno.ENOENT and os.path.islink(path):
            raise error(f"{name}: {what} is a symbolic link to a missing file") from None
        raise error(f"{name}: cannot read the {what} ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{name}: the {what} is {_kind(st.st_mode)}, not a regular file") from None
    return st


def read_bytes(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES,
               error: type = InputRefused) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes`` (see the module docstring)."""
    st = check_regular(path, what, error)
    name = printable(path)
    if st.st_size > max_bytes:
        raise error(f"{name}: the {what} is {st.st_size / MIB:.1f} MiB, more than the {max_bytes / MIB:g} MiB "
                    f"allowed")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # a FIFO swapped in meanwhile: no wait
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise error(f"{name}: the {what} is not a regular file")
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise error(f"{name}: cannot read the {what} ({e.strerror or e})") from None
    if len(data) > max_bytes:
        raise error(f"{name}: the {what} is more than the {max_bytes / MIB:g} MiB allowed (it grew while read)")
    return data


def read_text(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES,
              error: type = InputRefused) -> str:
    """UTF-8 text of ``path`` (a byte-order mark is dropped), read by :func:`read_bytes`."""
    data = read_bytes(path, what, max_bytes, error)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{printable(path)}: the {what} is not UTF-8 text (byte {e.start})") from None


def parse_json(raw: bytes | str, where: str, error: type = InputRefused):
    """A JSON document, nested at most :data:`MAX_JSON_DEPTH` deep; ``where`` names the file in errors."""
    try:
        data = json.loads(raw)
    except RecursionError:
        raise error(f"{printable(where)}: JSON nested too deeply (more than {MAX_JSON_DEPTH} levels)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{printable(where)}: not valid JSON ({e})") from None
    except ValueError as e:  # an integer literal too long to convert
        raise error(f"{printable(where)}: not valid JSON ({str(e).splitlines()[0][:120]})") from None
    if json_depth(data) > MAX_JSON_DEPTH:
        raise error(f"{printable(where)}: JSON nested too deeply (more than {MAX_JSON_DEPTH} levels)")
    return data


def json_depth(data) -> int:
    """Nesting depth of a decoded JSON value (a scalar is 0), without recursion."""
    deepest, todo = 0, [(data, 0)]
    while todo:
        v, d = todo.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            deepest = max(deepest, d + 1)
            if d + 1 <= MAX_JSON_DEPTH:
                todo.extend((x, d + 1) for x in v)
    return deepest


def read_json(path: str | Path, what: str = "JSON file", max_bytes: int = MAX_TEXT_BYTES,
              error: type = InputRefused):
    """The JSON document in ``path`` (read by :func:`read_bytes`, parsed by :func:`parse_json`)."""
    return parse_json(read_text(path, what, max_bytes, error), str(path), error)


def read_zip_member(zf, name: str, where: str, max_bytes: int = MAX_BLOB_BYTES, error: type = InputRefused) -> bytes:
    """Member ``name`` of the open ``zipfile.ZipFile`` ``zf``: refused when its declared size exceeds
    ``max_bytes``; inflation stops after ``max_bytes + 1`` bytes whatever the header says."""
    info = zf.getinfo(name)
    if info.file_size > max_bytes:
        raise error(f"{printable(where)}: declares {info.file_size / MIB:.0f} MiB uncompressed, more than the "
                    f"{max_bytes / MIB:g} MiB allowed")
    with zf.open(info) as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise error(f"{printable(where)}: inflates past the {max_bytes / MIB:g} MiB allowed")
    return data


def inflate(data: bytes, where: str, max_bytes: int = MAX_BLOB_BYTES, error: type = InputRefused) -> bytes:
    """zlib/deflate ``data`` inflated to at most ``max_bytes``."""
    d = zlib.decompressobj()
    try:
        out = d.decompress(data, max_bytes + 1)
    except zlib.error as e:
        raise error(f"{printable(where)}: not deflate data ({e})") from None
    if len(out) > max_bytes or d.unconsumed_tail:
        raise error(f"{printable(where)}: inflates past the {max_bytes / MIB:g} MiB allowed")
    return out


_LZFSE_END, _LZFSE_RAW = b"bvx$", b"bvx-"


def lzfse_declared_size(data: bytes, where: str, error: type = InputRefused) -> int:
    """The total output size LZFSE ``data`` declares in its block headers (read without decoding)."""
    total, pos = 0, 0
    while pos + 4 <= len(data):
        magic = data[pos:pos + 4]
        if magic == _LZFSE_END:
            return total
        if pos + 12 > len(data):
            break
        if magic == _LZFSE_RAW:
            n = struct.unpack_from("<I", data, pos + 4)[0]
            total, pos = total + n, pos + 8 + n
        elif magic in (b"bvx1", b"bvx2"):
            n, payload = _lzfse_v_block(data, pos, magic)
            total, pos = total + n, pos + payload
        elif magic == b"bvxn":
            n, size = struct.unpack_from("<II", data, pos + 4)
            total, pos = total + n, pos + 12 + size
        else:
            break
    raise error(f"{printable(where)}: not LZFSE data (no valid block header at byte {pos})")


def _lzfse_v_block(data: bytes, pos: int, magic: bytes) -> tuple[int, int]:
    """(declared output bytes, block length) of an LZFSE v1/v2 block at ``pos``."""
    n_raw = struct.unpack_from("<I", data, pos + 4)[0]
    if magic == b"bvx1":  # v1: n_raw, n_payload, then fixed-size fields and tables (772 bytes in all)
        return n_raw, 772 + struct.unpack_from("<I", data, pos + 8)[0]
    v0, v1, v2 = struct.unpack_from("<QQQ", data, pos + 8)  # v2: three packed words (lzfse_decode_v1's fields)
    header_size = v2 & 0xFFFFFFFF
    n_lit_payload, n_lmd_payload = (v0 >> 20) & 0xFFFFF, (v1 >> 40) & 0xFFFFF
    return n_raw, header_size + n_lit_payload + n_lmd_payload


def lzfse_decompress(data: bytes, where: str, max_bytes: int = MAX_BLOB_BYTES, error: type = InputRefused) -> bytes:
    """LZFSE ``data`` decoded, refused before decoding when its headers declare more than ``max_bytes``."""
    declared = lzfse_declared_size(data, where, error)
    if declared > max_bytes:
        raise error(f"{printable(where)}: declares {declared / MIB:.0f} MiB decompressed, more than the "
                    f"{max_bytes / MIB:g} MiB allowed")
    try:
        import liblzfse
    except ImportError:
        raise error("reading Record3D .r3d depth needs LZFSE: pip install pyliblzfse "
                    "(or pip install 'eligsir-o3d[phone]')") from None
    try:
        out = liblzfse.decompress(data)
    except Exception as e:  # liblzfse raises its own error type for corrupt data
        raise error(f"{printable(where)}: not LZFSE data ({e})") from None
    if len(out) > max_bytes:
        raise error(f"{printable(where)}: decompresses past the {max_bytes / MIB:g} MiB allowed")
    return out
