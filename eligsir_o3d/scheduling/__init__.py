"""Runtime policies: view scheduling, supervision fidelity and geometry growth, each with a plain counterpart."""

from __future__ import annotations

import dataclasses

from .base import FidelityPolicy, GrowthPolicy, MapContext, ViewPolicy
from .coarse_to_fine import CoarseToFine
from .fidelity import FidelityConfig, LoadAdaptiveFidelity
from .growth import GrowthConfig, TargetedGrowth
from .mcmc import MCMCConfig
from .fixed_work import FixedWorkConfig
from .keyframes import KeyframesConfig, StrideKeyframes
from .plain import FixedFidelity
from .seeding import NewSpaceSeeding, SeedingConfig
from .support import SupportConfig, SupportProbe
from .views import MapGuidedViews, ViewConfig

__all__ = ["ABLATIONS", "FidelityConfig", "FidelityPolicy", "FixedWorkConfig", "GrowthConfig", "GrowthPolicy",
           "KeyframesConfig", "LoadAdaptiveFidelity", "MCMCConfig", "MapContext", "MapGuidedViews",
           "SeedingConfig", "SupportConfig", "TargetedGrowth", "ViewConfig", "ViewPolicy", "get_policies"]

ABLATIONS = ("views", "fidelity", "growth")


def get_policies(cfg, offline: bool = False, n_source: int = 0,
                 camera=None) -> tuple[ViewPolicy, FidelityPolicy, GrowthPolicy]:
    """The (views, fidelity, growth) policies for a Config: EliGSiR's, or the plain one for each mechanism named in
    ``cfg.ablate`` (views -> fixed-stride keyframes with uniform replay, fidelity -> fixed native resolution,
    growth -> dense per-frame depth insertion). Views and growth share one support probe (one render per frame).

    ``offline``: the offline reference over ``n_source`` source frames instead: every frame retained (stride 1) and
    seeded where the map is empty, supervised by one coarse-to-fine schedule of ``clock.offline_updates`` (or
    ``offline_updates_per_frame`` per source frame) updates. ``camera``: the stream's (the fidelity floor follows
    its resolution, :mod:`.resolution`)."""
    unknown = [a for a in cfg.ablate if a not in ABLATIONS]
    if unknown:
        raise ValueError(f"unknown ablation(s) {unknown}; choose from {', '.join(ABLATIONS)}")
    if offline:
        return _offline_policies(cfg, n_source)
    probe = SupportProbe(cfg.support)
    if "views" in cfg.ablate:
        views = StrideKeyframes(cfg.keyframes)
    else:
        views = MapGuidedViews(cfg.views, probe)
    if "fidelity" in cfg.ablate:
        fidelity = FixedFidelity(cfg.fidelity.fixed_scale)
    else:
        fidelity = LoadAdaptiveFidelity(cfg.fidelity, camera)
    if "growth" in cfg.ablate:
        growth = NewSpaceSeeding(dataclasses.replace(cfg.seeding, dense=True), seed=cfg.seed, probe=cfg.support)
    else:
        growth = TargetedGrowth(cfg.growth, probe, seed=cfg.seed)
    return views, fidelity, growth


def _offline_policies(cfg, n_source: int) -> tuple[ViewPolicy, FidelityPolicy, GrowthPolicy]:
    from ..budget.clock import offline_updates

    c = cfg.clock
    views = StrideKeyframes(KeyframesConfig(every=1, newest_fraction=0.0, max_views=max(n_source, 1)))
    fidelity = CoarseToFine(offline_updates(c, n_source), c.offline_stages)  # coarse updates first, full res last
    growth = NewSpaceSeeding(cfg.seeding, seed=cfg.seed, probe=cfg.support)
    return views, fidelity, growth
