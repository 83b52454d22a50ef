"""Small checks that keep a command from destroying its own input or exhausting memory.

- :func:`refuse_overwriting_inputs`: an output path that is one of the command's inputs (the same path, or the
  same file through a symbolic or hard link) is refused before anything is read or written.
- :func:`check_image_size`: a rendered image larger than :data:`MAX_RENDER_PIXELS` is refused (``render --scale``).
- :func:`check_tsdf_memory`: a TSDF mesh whose voxel grid would need more than ``limit_gib`` is refused
  (``export --mesh --voxel-size``), naming the smallest voxel size that fits.
All raise ``ValueError`` with one line (exit 2).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

MAX_RENDER_PIXELS = 100_000_000  # 100 MPix per rendered image (an 8K frame is 33 MPix)
TSDF_BYTES_PER_BLOCK = 16 ** 3 * 5 * 4  # block_resolution 16, tsdf + weight + rgb float32


def _same(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)  # hard links and symbolic links too
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def refuse_overwriting_inputs(outputs: dict[str, str | Path | None], inputs: dict[str, str | Path | None]) -> None:
    """``outputs`` / ``inputs``: option name -> path (None: not given). Raise ValueError when an output is an input
    or two outputs are the same file."""
    outs = [(k, Path(v)) for k, v in outputs.items() if v is not None]
    ins = [(k, Path(v)) for k, v in inputs.items() if v is not None]
    for name, out in outs:
        for iname, inp in ins:
            if _same(out, inp):
                raise ValueError(f"{out}: {name} would overwrite the input {iname} ({inp}); write it to another path")
    for i, (name, out) in enumerate(outs):
        for other, out2 in outs[i + 1:]:
            if _same(out, out2):
                raise ValueError(f"{out}: given as both {name} and {other}; give each its own path")


def check_image_size(width: int, height: int, what: str = "the rendered image") -> None:
    if width * height > MAX_RENDER_PIXELS:
        raise ValueError(f"{what} would be {width}x{height} ({width * height / 1e6:.0f} MPix), more than the "
                         f"{MAX_RENDER_PIXELS / 1e6:.0f} MPix allowed; use a smaller --scale")


def tsdf_memory_bytes(means: np.ndarray, voxel_size: float) -> float:
    """Estimated bytes of a TSDF voxel-block grid covering the surfaces of a map with centres ``means`` [N, 3]
    (metres): the box around the central 98% of the centres, its faces' area as the surface, two blocks thick."""
    if len(means) == 0:
        return 0.0
    lo, hi = np.percentile(means, 1, axis=0), np.percentile(means, 99, axis=0)
    e = np.maximum(hi - lo, voxel_size * 16)
    area = 2.0 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2])
    blocks = 2.0 * area / (16.0 * voxel_size) ** 2
    return blocks * TSDF_BYTES_PER_BLOCK


def check_tsdf_memory(means: np.ndarray, voxel_size: float, limit_gib: float = 8.0) -> None:
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"--voxel-size must be a positive number of metres, got {voxel_size}")
    need = tsdf_memory_bytes(means, voxel_size)
    limit = limit_gib * 2 ** 30
    if need > limit:
        smallest = voxel_size * math.sqrt(need / limit)
        raise ValueError(f"--voxel-size {voxel_size:g}: a TSDF of this map at that voxel size needs about "
                         f"{need / 2 ** 30:.0f} GiB (limit {limit_gib:g} GiB); use --voxel-size {smallest:.4f} or "
                         f"larger")
