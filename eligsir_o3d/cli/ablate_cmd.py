"""``eligsir ablate PATH``: the paper's Table III for one sequence, the full method and each ablation under the same
held-out split and budget, run one after the other (:mod:`eligsir_o3d.eval.ablation` makes the table).

It takes ``eligsir map``'s options, by the same names and with the same defaults (the table of :mod:`.map_options`,
less those that make no sense for several runs: ``--ablate``, ``--rerun``, ``--resume``, ``--checkpoint-every``,
``--force-unlock`` and the live view), applied to every variant, plus its own:

    eligsir ablate ../shared/data/7scenes_redkitchen_jpg1000 --max-frames 300 --out runs/ablation
    eligsir ablate SEQ --variants full,views --seeds 0,1,2 --speed 0.1 --eval-every 0 --out D
    eligsir ablate --out D --table-only --seeds 0,1,2          # the table again from D's results folders

The budget is ``eligsir map``'s: the deterministic cost-model clock by default, so every variant gets the same
modelled compute and a variant whose updates cost more gets fewer of them; ``--speed 1`` (the default) replays at
the recorded rate, as the paper's online ablations run.
"""

from __future__ import annotations

import inspect
import logging
import sys
import time
from pathlib import Path
from typing import Optional

import typer

from .commands import fail
from .map_options import PANELS, PATH, _opt, map_options

ABLATION = "Ablation"
NOT_FOR_ABLATIONS = ("ablate", "rerun", "resume", "checkpoint_every", "force_unlock", "view", "view_port",
                     "view_host")
OWN_OPTIONS = [
    ("variants", str, _opt("full,fidelity,growth,views", "Variants to run, comma-separated: full and any --ablate "
                           "value.", ABLATION)),
    ("seeds", Optional[str], _opt(None, "Run every variant once per seed (OUT/<variant>-s<seed>); the table gives "
                                  "the means +- one seed sd.", ABLATION, metavar="S,S,...")),
    ("table_only", bool, _opt(False, "Only make the table again, from OUT/*/metrics.json.", ABLATION,
                              "--table-only")),
]


def with_ablate_options(fn):
    """``fn(**options)`` with ``eligsir map``'s options (less :data:`NOT_FOR_ABLATIONS`) and :data:`OWN_OPTIONS`."""
    table = [PATH, *(o for panel in PANELS for o in panel if o[0] not in NOT_FOR_ABLATIONS), *OWN_OPTIONS]
    fn.__signature__ = inspect.Signature([inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default,
                                                            annotation=tp) for name, tp, default in table])
    return fn


def parse_seeds(text: str | None) -> list[int] | None:
    """``"0,1,2"`` -> [0, 1, 2]; None: one run per variant, at the config's (or ``--seed``'s) seed."""
    if text is None:
        return None
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--seeds must be comma-separated integers, got {text!r}") from None
    if not seeds:
        raise ValueError("--seeds names no seed")
    return seeds


def run_variants(path: str, out: Path, kw: dict, variants: list[str], seeds: list[int] | None) -> None:
    """One ``eligsir map`` run a variant (and seed) into ``out/<variant>[-s<seed>]``."""
    from ..eval.ablation import VARIANTS, run_dir
    from ..run.options import resolve
    from ..run.pipeline import run_mapping

    for variant in variants:
        for seed in seeds or [None]:
            o = map_options({**kw, "ablate": list(VARIANTS[variant])})
            if seed is not None:
                o.seed = seed
            cfg, opts = resolve(o)
            opts.overwrite = kw["overwrite"]
            t0 = time.perf_counter()
            run_mapping(path, run_dir(out, variant, seed), cfg, opts)
            tag = variant if seed is None else f"{variant} seed {seed}"
            typer.echo(f"[{tag}] done in {time.perf_counter() - t0:.0f} s wall")


@with_ablate_options
def ablate_cmd(**kw) -> None:
    """The paper's Table III for one sequence: the full method and each ablation, same split, same budget."""
    from ..eval.ablation import VARIANTS, write_table

    logging.basicConfig(level=logging.WARNING if kw["quiet"] else logging.INFO, format="%(levelname)s %(message)s")
    variants = [v.strip() for v in kw.pop("variants").split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        fail(f"unknown variant(s) {unknown}; choose from {', '.join(VARIANTS)}")
    out = Path(kw["out"] or "runs/ablation")
    table_only = kw.pop("table_only")
    if not table_only and kw["path"] is None:
        fail("missing the sequence PATH (or --table-only)")
    try:
        seeds = parse_seeds(kw.pop("seeds"))
        if not table_only:
            run_variants(kw["path"], out, kw, variants, seeds)
        out.mkdir(parents=True, exist_ok=True)
        table, checks, fig = write_table(out, variants, seeds, "eligsir ablate " + " ".join(sys.argv[2:]))
    except (ValueError, OSError, RuntimeError) as e:
        fail(str(e), getattr(e, "exit_code", 2))
    typer.echo(table)
    for c in checks:
        typer.echo(c)
    if fig:
        typer.echo(f"fidelity trace: {fig}")
