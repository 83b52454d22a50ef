"""Memory accounting: peak and current resident set size, and what the map and the retained views hold.

What bounds memory in a long run (nothing else grows with the number of frames):
- Gaussians: ``config.max_gaussians`` - growth policies never add beyond it (MCMC relocates instead).
- Retained views: ``max_views`` of the view policy (``config.views.max_views``, or ``config.keyframes.max_views``
  for the plain policy); beyond it a view is *dropped* (the plain policy evicts the oldest, Map-Guided View
  Scheduling the lowest-priority inactive one). Nothing is spilled to disk: a dropped view is gone, and a
  checkpoint stores only the views retained when it is written. One view at source resolution costs
  16 bytes per pixel (float32 colour and depth), plus its cached lower-resolution copies (at most 1/3 more):
  ~4.9 MB at 640x480, so 400 views are ~2-2.6 GB.
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
    """MiB held by the Gaussian parameters and their Adam moments (two per parameter)."""
    params = sum(_nbytes(p) for p in gmap.params.values())
    moments = 0
    for name, opt in gmap.optimizers.items():
        for s in opt.state.get(gmap.params[name], {}).values():
            if hasattr(s, "element_size") and s.ndim > 0:
                moments += _nbytes(s)
    return (params + moments) / (1024.0 * 1024.0)


def memory_report(rec) -> dict:
    """Peak/current RSS and the map's and retained views' share, for metrics.json and logs."""
    views = list(rec.views.views)
    return {"peak_rss_mb": peak_rss_mb(), "rss_mb": current_rss_mb(), "gaussians": len(rec.gmap),
            "max_gaussians": rec.config.max_gaussians, "map_mb": map_memory_mb(rec.gmap),
            "retained_views": len(views), "views_mb": views_memory_mb(views)}
