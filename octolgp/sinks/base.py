"""The sink protocol: what an online map tells the outside world, and the null sink.

A map calls its sink unconditionally (no ``if visualize:`` branches in the
pipeline). The sink gets each accepted scan and, after each step, what changed:
the refitted leaves' voxel values as plain arrays (:class:`LeafView`), never the
store or the map itself.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray, Scan

if TYPE_CHECKING:
    from octolgp.mapping.update import ScanUpdate


@dataclass(frozen=True)
class LeafView:
    """One refitted leaf, as a sink sees it.

    Attributes
    ----------
    key : int
        Packed leaf key (stable: an entity path can use it).
    lo, hi : ndarray of shape (d,)
        The leaf's box, metres, world frame.
    centres : ndarray of shape (V, d)
        Voxel centres, metres, world frame, in flat voxel order (x fastest).
    prob, mean, var : ndarray of float32, shape (V,) or (1,)
        P(occupied), latent mean and variance per voxel (one value when pruned).
    pruned : bool
    """

    key: int
    lo: FloatArray
    hi: FloatArray
    centres: FloatArray
    prob: NDArray[np.float32]
    mean: NDArray[np.float32]
    var: NDArray[np.float32]
    pruned: bool


@dataclass(frozen=True)
class MapChange:
    """What one step changed in the map.

    Attributes
    ----------
    dim : int
    resolution : float
        Voxel edge, metres.
    side : int
        Voxels per leaf edge.
    signal_variance : float
        The GP prior variance (1 before hyperparameters exist), to scale variances.
    leaves : iterable of LeafView
        The refitted leaves, produced as the sink iterates (read them once; a sink
        that ignores them costs nothing).
    removed : tuple of int
        Packed keys of leaves that left the map (a pose correction emptied them).
    """

    dim: int
    resolution: float
    side: int
    signal_variance: float
    leaves: Iterable[LeafView]
    removed: tuple[int, ...] = ()


class Sink(Protocol):
    """Receives a map's events (:class:`NullSink`, :class:`octolgp.sinks.rerun.RerunSink`).

    A sink may also have ``on_provisional(update, provisional)``: a map still learning its
    hyperparameters calls it after each step that only buffered a scan, with
    ``provisional``, a callable that builds the provisional map of the buffered scans
    and returns all its leaves as a :class:`MapChange` (a learning and a fit: call it
    when the drawing is worth that).
    """

    def on_scan(self, scan: Scan, index: int) -> None:
        """An accepted scan, number ``index`` from 1 (before buffering or integration)."""
        ...

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        """A step's summary and the leaves it refitted."""
        ...


class NullSink:
    """Where map events go when nothing listens: every method does nothing."""

    def on_scan(self, scan: Scan, index: int) -> None:
        """Ignore an accepted scan."""

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        """Ignore a step."""
