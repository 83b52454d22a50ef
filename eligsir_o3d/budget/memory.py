"""Memory accounting: peak and current resident set size, and what the map and the retained views hold.

What bounds memory in a long run (nothing else grows with the number of frames):
- Gaussians: ``config.max_gaussians`` - growth policies never add beyond it (MCMC relocates instead).
- Retained views: ``max_views`` of the view policy (``config.views.max_views``, or ``config.keyframes.max_views``
  for the plain policy); beyond it a view is *dropped* (the plain policy evicts the oldest, Map-Guided View
  Scheduling the lowest-priority inactive one). Nothing is spilled to disk: a dropped view is gone, and a
  checkpoint stores only the views retained when it is written. One view at source resolution costs
  16 bytes per pixel (float32 colour and depth), plus its cached lower-resolution copies (at most 1/3 more):
  ~4.9 MB at 640x480, so 400 views are ~2-2.6 GB.

:func:`cap_allowance_mb` turns these bounds into MiB for a config (the soak benchmark's memory check,
benchmarks/budget/soak.py).
"""

from __future__ import annotations

import resource
import sys


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (``getrusage``; Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def current_rss_mb() -> float | None:
    """Current resident set size, MiB (Linux ``/proc/self/statm``; None elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * resource.getpagesize() / (1024.0 * 1024.0)


def _nbytes(t) -> int:
    return t.numel() * t.element_size() if t is not None else 0


def views_memory_mb(frames) -> float:
    """MiB held by the images of ``frames`` (a view policy's ``views``): source colour and depth plus cached
    resampled copies."""
    total = 0
    for f in frames:
        total += _nbytes(f.color) + _nbytes(f.depth)
        for color, depth, _ in getattr(f, "_pyramid", {}).values():
            if color is not f.color:
                total += _nbytes(color) + _nbytes(depth)
    return total / (1024.0 * 1024.0)


def map_memory_mb(gmap) -> float:
    """MiB held by the Gaussian parameters and their Adam moments (two per parameter), the buffers' whole
    capacity."""
    return gmap.nbytes() / (1024.0 * 1024.0)


def memory_report(rec) -> dict:
    """Peak/current RSS and the map's and retained views' share, for metrics.json and logs."""
    views = list(rec.views.views)
    return {"peak_rss_mb": peak_rss_mb(), "rss_mb": current_rss_mb(), "gaussians": len(rec.gmap),
            "max_gaussians": rec.config.max_gaussians, "map_mb": map_memory_mb(rec.gmap),
            "retained_views": len(views), "views_mb": views_memory_mb(views)}


def reset_peak_rss() -> bool:
    """Restart the peak RSS count (Linux: ``/proc/self/clear_refs`` 5 resets the high-water mark that ``getrusage``
    reports), so a run inside a longer process (a test session) measures its own peak. False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def retained_views_bound(cfg) -> int:
    """The retained-view bound of the view policy ``cfg`` builds (the plain policy's when views are ablated)."""
    return cfg.keyframes.max_views if "views" in cfg.ablate else cfg.views.max_views


def cap_allowance_mb(cfg, width: int, height: int) -> dict:
    """MiB that the caps of ``cfg`` allow the map and the retained views (``width`` x ``height`` source pixels) to
    hold: ``max_gaussians`` x 4 copies (parameter, gradient, two Adam moments) of each Gaussian's float32s (means 3,
    scales 3, quaternion 4, opacity 1, SH 3 (sh_degree + 1)^2), doubled for an update's transient per-Gaussian
    tensors; ``max_views`` x 16 bytes per pixel x 4/3 (cached resampled copies)."""
    per_gaussian = (11 + 3 * (cfg.sh_degree + 1) ** 2) * 4 * 4 * 2  # bytes: 4 copies, x2 transient
    views = retained_views_bound(cfg)
    return {"gaussians_mb": cfg.max_gaussians * per_gaussian / (1024.0 * 1024.0),
            "views_mb": views * width * height * 16 * (4 / 3) / (1024.0 * 1024.0),
            "bytes_per_gaussian": per_gaussian, "max_gaussians": cfg.max_gaussians, "max_views": views}


def structure_sizes(rec) -> dict:
    """Sizes of what could grow with the stream: Gaussians, retained views, the growth policy's evidence voxels,
    the view policy's microcells and the fidelity trace (None where the policy keeps no such structure)."""
    sizes = {"gaussians": len(rec.gmap), "views": len(rec.views.views)}
    for key, owner, name in (("evidence_voxels", rec.growth, "voxels"), ("microcells", rec.views, "cells"),
                             ("fidelity_trace", rec.fidelity, "trace")):
        held = getattr(owner, name, None)
        sizes[key] = len(held) if held is not None else None
    return sizes
