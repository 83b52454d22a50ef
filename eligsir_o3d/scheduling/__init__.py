"""Runtime policies: view scheduling, supervision fidelity and geometry growth, each with a plain counterpart."""

from __future__ import annotations

from .base import FidelityPolicy, GrowthPolicy, MapContext, ViewPolicy
from .plain import FixedFidelity, NewSpaceSeeding, StrideKeyframes

__all__ = ["FidelityPolicy", "GrowthPolicy", "MapContext", "ViewPolicy", "get_policies"]


def get_policies(cfg) -> tuple[ViewPolicy, FidelityPolicy, GrowthPolicy]:
    """The (views, fidelity, growth) policies for a Config: EliGSiR's, or the plain one for each ablated mechanism."""
    views = StrideKeyframes(cfg.stride)
    fidelity = FixedFidelity(cfg.fixed_scale)
    growth = NewSpaceSeeding(cfg.seeding, seed=cfg.seed)
    return views, fidelity, growth
