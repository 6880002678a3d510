"""Leaf engines: how a map turns scans into evidence per leaf and fits its leaves.

``lattice`` (the default, :mod:`octolgp.engines.lattice`) and ``exact`` (the paper's
method and the reference, :mod:`octolgp.engines.exact`) share one seam,
:class:`octolgp.engines.base.LeafEngine`; :func:`engine_for` picks a config's.
"""

from __future__ import annotations

from octolgp.config import MapConfig
from octolgp.engines.base import Evidence, LeafEngine, LeafFit
from octolgp.engines.exact import ExactEngine
from octolgp.engines.lattice import LatticeEngine

__all__ = ["Evidence", "LeafEngine", "LeafFit", "engine_for"]


def engine_for(config: MapConfig) -> LeafEngine:
    """The leaf engine ``config.online.engine`` names, for a map of this (resolved) config."""
    if config.online.engine == "exact":
        return ExactEngine(config)
    return LatticeEngine(config)
