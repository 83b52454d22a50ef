"""``eligsir calibrate [--force]``: show the cached cost-model fit of this machine, device and renderer (when and
under what conditions it was taken, whether it is still reused), or take it again."""

from __future__ import annotations

import json
import logging
from typing import Optional

import typer

from .commands import Renderer, fail, setup_logging


def describe(path, data: dict | None) -> list[str]:
    """Lines about the cache file ``path`` holding ``data`` (None: absent)."""
    from ..budget import conditions

    if data is None:
        return [f"no cost model calibrated yet for this machine, device and renderer ({path}); "
                f"eligsir map calibrates on first use, or run eligsir calibrate --force"]
    c = data.get("conditions") or {}
    why = conditions.unusable_reason(data.get("conditions"))
    lines = [f"cost model {path}", f"  taken {data.get('created', '?')}"]
    if c:
        lines.append(f"  conditions: load average {c.get('load_1m', float('nan')):.2f} on {c.get('cpus', '?')} CPU(s), "
                     f"quiet check spread {c.get('spread', float('nan')):.2f}x, kernel {c.get('kernel', '?')}"
                     + (f", busy: {c['busy']}" if c.get("busy") else ""))
    lines.append("  terms: " + json.dumps(data.get("model", {}), sort_keys=True))
    lines.append("  reused by the next run" if why is None else f"  NOT reused ({why}): the next run calibrates again")
    return lines


def calibrate_cmd(
    force: bool = typer.Option(False, "--force", help="Calibrate again now (a few seconds) and cache the fit."),
    device: str = typer.Option("cpu", help="Device to calibrate for."),
    renderer: Renderer = typer.Option(Renderer.auto, help="Renderer to calibrate for."),
    config: Optional[str] = typer.Option(None, help="config.json whose settings the fit is for (pose refinement)."),
) -> None:
    """Show the calibrated cost model of this machine (and the conditions it was taken under), or --force a new one."""
    from ..budget.calibrate import cache_path, machine_key, read_cached
    from ..config import Config

    setup_logging()
    try:
        cfg = (Config.load(config) if config else Config())
        cfg.device, cfg.renderer = device, renderer.value
        cfg = cfg.resolve()
        path = cache_path(machine_key(cfg.device, cfg.renderer))
        if force:
            from ..export.views import DEFAULT_CAMERA
            from ..mapper import Reconstructor

            rec = Reconstructor(DEFAULT_CAMERA, cfg.device, cfg)
            rec.calibrate(force=True)
    except (ValueError, OSError, RuntimeError) as e:
        fail(str(e), getattr(e, "exit_code", 2))
    for line in describe(path, read_cached(path)):
        typer.echo(line)
