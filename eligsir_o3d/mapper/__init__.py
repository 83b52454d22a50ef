"""The online mapper: :class:`Reconstructor` (what users integrate frames into), composed of its
:class:`MapperState` (what a checkpoint saves), with :class:`MappingStats` (the protocol's compute accounting)."""

from .reconstructor import Reconstructor
from .state import MapperState, MappingStats

__all__ = ["MapperState", "MappingStats", "Reconstructor"]
