"""Scans → evidence per leaf, for the map's engine: checking scans, chunks and batches.

:func:`check_scan` is the gate every scan passes before anything changes.
:func:`gather_batch` runs the engine's evidence step (:meth:`octolgp.engines.base.
LeafEngine.evidence`) over chunks of scans in time order, so a whole log's evidence is
gathered with transient memory bounded by the chunk. :func:`batch_bounds` cuts the
leaves to fit into batches. Everything here reads the store through a lookup function
and never writes it: the map applies the result.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from octolgp.config import MapConfig
from octolgp.engines.base import LeafEngine, LeafFit, Lookup
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan, check_scan_size


def check_scan(scan: object, config: MapConfig, grid: LeafGrid) -> Scan:
    """Validate a scan for a map: type, size, dimension and addressable range.

    The halo of a leaf at the edge of the tree must stay addressable too, so the
    usable range is the addressable range less two leaf edges on each side. Returns
    the scan the map is built from: rounded to ``OnlineConfig.scan_precision``.

    Raises
    ------
    OctolgpError
        Naming the field and the first offending row.
    """
    if not isinstance(scan, Scan):
        raise OctolgpError(f"scan must be a Scan, got {type(scan).__name__}")
    check_scan_size(scan, config.online.max_scan_points)
    if scan.dim != config.dim:
        raise OctolgpError(f"scan is {scan.dim}D but MapConfig.dim is {config.dim}")
    low, high = addressable_range(config.resolution, config.tree_depth)
    margin = 2 * grid.edge
    for name, pts in (("scan.origin", scan.origin[None, :]), ("scan.points", scan.points)):
        bad = (pts < low + margin) | (pts >= high - margin)
        if bad.any():
            row = int(np.flatnonzero(bad.any(axis=1))[0])
            raise OctolgpError(
                f"{name} row {row} ({pts[row].tolist()}) is outside the addressable range "
                f"[{low + margin:g}, {high - margin:g}) m of this map"
            )
    return map_scans([scan], config)[0]


def map_scans(scans: list[Scan], config: MapConfig) -> list[Scan]:
    """The scans a map with ``config`` is built from: rounded to ``OnlineConfig.scan_precision``."""
    precision = config.online.scan_precision
    return scans if precision is None else [s.rounded(precision) for s in scans]


def scan_chunks(scans: list[Scan], beams: int) -> Iterator[list[Scan]]:
    """Consecutive runs of scans holding about ``beams`` beams each (at least one scan)."""
    chunk: list[Scan] = []
    total = 0
    for s in scans:  # one iteration per scan
        chunk.append(s)
        total += len(s)
        if total >= beams:
            yield chunk
            chunk, total = [], 0
    if chunk:
        yield chunk


def gather_batch(
    scans: list[Scan],
    engine: LeafEngine,
    lookup: Lookup,
    chunk_beams: int,
    stats: dict[str, float],
) -> tuple[dict[int, Leaf], set[int], int]:
    """Every scan's evidence, chunk by chunk in time order, as new leaves by key.

    Chunks in time order give exactly the leaves of all scans at once (each engine
    applies its evidence rule in time order) while bounding the transient arrays of the
    assignment by the chunk, not the log.

    Parameters
    ----------
    scans : list of Scan
        Checked scans, in time order.
    engine : LeafEngine
        The map's engine.
    lookup : callable
        The map's current leaf of a packed key, or ``None``; only read.
    chunk_beams : int
        Beams per chunk.
    stats : dict of str to float
        ``training`` and ``assign`` seconds are written here.

    Returns
    -------
    leaves : dict of int to Leaf
        The leaves with new evidence, new objects, in first-touch order.
    refit : set of int
        The keys among them whose GP inputs changed (the others are only stored).
    new_items : int
    """
    gathered: dict[int, Leaf] = {}
    refit: set[int] = set()
    new_items = 0
    stats["training"] = stats["assign"] = 0.0

    def current(key: int) -> Leaf | None:
        leaf = gathered.get(key)
        return leaf if leaf is not None else lookup(key)

    for chunk in scan_chunks(scans, chunk_beams):  # a few hundred thousand beams each
        evidence = engine.evidence(chunk, current, stats)
        new_items += evidence.new_items
        for key, leaf in evidence.changed:  # one iteration per leaf that gained evidence
            gathered[key] = leaf
            refit.add(key)
        for key, leaf in evidence.kept:  # one iteration per leaf with new counts only
            gathered[key] = leaf
    return gathered, refit, new_items


def batch_bounds(sizes: list[int], items: int) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` runs of consecutive entries whose sizes sum to about ``items`` each.

    A run closes at the first entry that brings its sum to ``items`` or more; the last
    run may be smaller. Used to cut leaves (or clusters) into batches of work.
    """
    lo = total = 0
    for i, size in enumerate(sizes):  # one iteration per entry
        total += size
        if total >= items:
            yield lo, i + 1
            lo, total = i + 1, 0
    if lo < len(sizes):
        yield lo, len(sizes)


LeafFitter = Callable[[list[int], list[Leaf]], Iterator[tuple[list[int], list[LeafFit]]]]
"""Leaves with evidence → the same leaves fitted, batch by batch (local threads or a
cluster; :meth:`octolgp.mapping.online.OnlineMap.insert_batch`)."""
