"""Calibration: fit the cost model to the machine, device and renderer a run is on, and cache it.

The shipped cost model was fitted on one 2-core CPU with the ``cpu`` renderer; on a GPU (gsplat) or another
machine its modelled seconds are wrong by up to orders of magnitude, so the deterministic budget would grant far
more or far fewer updates than the machine can spend. :func:`calibrate` maps a few frames into a scratch
Reconstructor (same camera, device, renderer and policies; the caller's map is untouched) and times
``updates_per_scale`` updates at each supervision scale after each frame, then fits :meth:`CostModel.fit`.

:func:`cached_cost_model` keeps one fit per machine (host, CPU, device name, renderer, torch and package
versions) as JSON under the user's cache directory (``$XDG_CACHE_HOME/eligsir_o3d``, default ``~/.cache``):
the first run on a machine calibrates (seconds), later ones reuse it while its recorded conditions allow
(:mod:`.conditions`: not taken on a busy machine, not stale); ``eligsir calibrate [--force]`` shows / redoes it.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_write_text
from .cost import CostModel, priced_gaussians

SCALES = (0.125, 0.25, 0.5, 1.0)
MIN_GAUSSIAN_SPAN = 3.0  # largest / smallest map size among the timed updates needed for a full fit


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "eligsir_o3d"


def machine_key(device, renderer: str) -> dict:
    """What a fit depends on: this machine, the device and the renderer (and the code that runs)."""
    import torch

    from .._version import __version__

    dev = torch.device(device)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else _cpu_name()
    return {"host": platform.node(), "machine": platform.machine(), "cpus": os.cpu_count(), "device": str(dev),
            "device_name": name, "renderer": renderer, "torch": torch.__version__, "eligsir_o3d": __version__,
            "numba_layer": "tbb" if _on_tbb() else "other",
            "fit": 6}  # raised whenever the kernels' cost changes, so that older cached fits are retaken
    # (lab: calibration-fit-versions). The layer is a key of its own: a process that imported Open3D before
    # eligsir_o3d runs numba on OpenMP (eligsir_o3d/runtime/tbb.py), slower on 2 threads


def _on_tbb() -> bool:
    from ..runtime.jit import ON_TBB  # numba loads here, with the kernels' first user

    return bool(ON_TBB)


def cache_path(key: dict) -> Path:
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return cache_dir() / f"cost-{key['renderer']}-{digest}.json"


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "cpu"


def time_updates(rec, frames, scales=SCALES, updates_per_scale: int = 2, warmup_frames: int = 1):
    """Integrate ``frames`` into Reconstructor ``rec`` (no updates of its own) and time ``updates_per_scale``
    updates at each scale after each; returns (update rows ``(pixels, gaussians, seconds)``, frame rows
    ``(gaussians, seconds)``). The first ``warmup_frames`` frames' timings are dropped (caches, compilation)."""
    upd, frm = [], []
    for n, frame in enumerate(frames):
        t0 = time.perf_counter()
        rec.integrate(frame, updates=0)
        dt = time.perf_counter() - t0
        if n >= warmup_frames:
            frm.append((priced_gaussians(rec), dt))
        for s in scales:
            for _ in range(updates_per_scale):
                px = rec.stats.supervised_pixels
                t0 = time.perf_counter()
                if rec.optimize(1, scale=s) == 0:
                    break
                dt = time.perf_counter() - t0
                g = priced_gaussians(rec)  # the Gaussians the update just paid for (in its view)
                if n >= warmup_frames:
                    upd.append((rec.stats.supervised_pixels - px, g, dt))
    return np.array(upd, dtype=np.float64).reshape(-1, 3), np.array(frm, dtype=np.float64).reshape(-1, 2)


def calibrate(rec, frames=None, *, n_frames: int = 6, updates_per_scale: int = 3, scales=SCALES,
              make_scratch=None) -> tuple[CostModel, dict]:
    """Fit a cost model for ``rec``'s device and renderer: (model, report). ``frames``: Frames with poses to map
    (default: ``n_frames`` of the embedded synthetic room at ``rec``'s image size). ``make_scratch``: builds the
    scratch Reconstructor (default: ``type(rec)(rec.camera or the room's camera, rec.device, rec.config)``)."""
    from ..datasets import open_sequence

    if frames is None:
        cam = rec.camera
        seq = open_sequence("synthetic", n_frames=max(n_frames, 2), width=cam.width, height=cam.height)
        frames, camera = [seq.frame(i) for i in range(len(seq))][:n_frames], seq.camera
    else:
        frames = list(frames)[:max(n_frames, 2)] if n_frames else list(frames)
        camera = frames[0].camera
    make = make_scratch or (lambda cam: type(rec)(cam, str(rec.device), copy.deepcopy(rec.config)))
    scratch = make(camera)
    scratch.warmup()
    t0 = time.perf_counter()
    upd, frm = time_updates(scratch, frames, scales, updates_per_scale)
    span = float(upd[:, 1].max() / max(1.0, upd[:, 1].min())) if len(upd) else 1.0
    if span >= MIN_GAUSSIAN_SPAN:
        model = CostModel.fit(upd, frm)
    else:
        # A few frames of one stream hold maps of about one size: the Gaussian terms cannot be told apart from
        # the constant ones (a full fit gave them 0, and the budget then outgrew the machine as the map grew).
        # Keep the shape of the shipped fit (made over map sizes of 1k-20k) and fit only its speed, below.
        model = CostModel()
    # least squares on relative error is pulled by the long tail of a shared machine (an update that waited for
    # the CPU): scale the fit so that its median prediction matches the median measurement
    k = 1.0 / float(np.median(model.ratios(upd)))
    model = CostModel(**{name: v * k for name, v in model.to_dict().items()})
    if len(frm):
        # the per-frame fixed work (support render, growth, view bookkeeping) as measured, not scaled with the
        # updates: under load the update and frame terms drift apart (lab: calibration-frame-term); the median,
        # for the load's long tail
        model.frame_s = float(np.median(np.maximum(frm[:, 1] - model.gaussian_s * frm[:, 0], 0.0)))
    ratios = model.ratios(upd)
    report = {"samples": int(len(upd)), "seconds": time.perf_counter() - t0,
              "fit": "full" if span >= MIN_GAUSSIAN_SPAN else "shipped shape, this machine's speed",
              "speed_vs_shipped": float(k) if span < MIN_GAUSSIAN_SPAN else None,
              "median_predicted_over_measured": float(np.median(ratios)),
              "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
              "gaussians": [int(upd[:, 1].min()), int(upd[:, 1].max())] if len(upd) else None}
    return model, report


def read_cached(path: Path) -> dict | None:
    """The cache file's record, or None (absent or damaged)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def cached_cost_model(rec, frames=None, force: bool = False, **kw) -> tuple[CostModel, dict]:
    """The cached fit for ``rec``'s machine, device and renderer, calibrating (and caching) it on first use, when
    ``force``, or when the cached one's conditions make it unusable (:mod:`.conditions`). Returns (model, info)
    where info names the cache file, whether it was just calibrated and the conditions."""
    import logging

    from . import conditions

    log = logging.getLogger("eligsir_o3d")
    key = machine_key(rec.device, rec.config.renderer)
    path = cache_path(key)
    data = None if force else read_cached(path)
    if data is not None and data.get("key") == key:
        why = conditions.unusable_reason(data.get("conditions"))
        if why is None:
            try:
                return CostModel.from_dict(data["model"], str(path)), {
                    "source": "calibrated", "cache": str(path), "fresh": False,
                    "conditions": data.get("conditions"), **data.get("report", {})}
            except (ValueError, KeyError, TypeError):
                pass  # a damaged cache file is replaced below
        else:
            log.warning("cost model %s is not reused: %s; calibrating again", path, why)
    before = conditions.measure()
    model, report = calibrate(rec, frames, **kw)
    after = conditions.measure()
    cond = {**before, "busy": before["busy"] or after["busy"], "load_1m_after": after["load_1m"]}
    if cond["busy"]:
        log.warning("the cost model was calibrated on a busy machine (%s): this run's budget may be too small; the "
                    "fit will not be reused (later runs calibrate again; --cost-model shipped is load-free)",
                    cond["busy"])
    atomic_write_text(path, json.dumps({"key": key, "model": model.to_dict(), "report": report, "conditions": cond,
                                        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}, indent=2))
    return model, {"source": "calibrated", "cache": str(path), "fresh": True, "conditions": cond, **report}
