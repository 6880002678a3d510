"""The log-odds occupancy grid: the "OGM" baseline of Kim & Kim (IROS 2013), Table II.

It follows OctoMap's ``insertPointCloud`` with its default sensor model
(:class:`~octolgp.config.OgmConfig`). For each scan it first computes the update:

* each beam's end voxel is a hit;
* the voxels the beam passes through, from the origin's up to but excluding the
  end's, are misses;
* a beam at least ``Scan.max_range`` long is a no-return: misses along it up to
  ``max_range``, and no hit;
* a voxel is updated at most once per scan, and a hit wins over a miss.

It then applies the update, ``log_odds += logodds(prob_hit or prob_miss)``,
clamped to ``[logodds(clamping_thres_min), logodds(clamping_thres_max)]``.

Scans are processed in batches, with the clamped updates applied in scan order,
so the result equals OctoMap's scan-by-scan insertion.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.config import MapConfig, OgmConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import (
    addressable_mask,
    addressable_range,
    coord_to_key,
    key_to_coord,
    pack_keys,
    unpack_keys,
)
from octolgp.geometry.raycast import traverse_voxels
from octolgp.observations import sorted_contains
from octolgp.scan import Scan, as_points

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
LogOddsArray = NDArray[np.float32]

# An update code is ``packed_key << 15 | scan_in_batch << 1 | is_hit``; sorting the
# codes orders updates by voxel, then by scan. Packed keys take at most 48 bits.
_SCAN_BITS = 14
_MAX_BATCH_SCANS = 1 << _SCAN_BITS
_MAX_BATCH_VOXELS = 1 << 22  # bound on traversed voxels held at once


def logodds(probability: float) -> float:
    """Return ``log(p / (1 - p))``, OctoMap's ``logodds``."""
    return float(np.log(probability / (1.0 - probability)))


def clamp_log_odds(log_odds: LogOddsArray, ogm: OgmConfig) -> LogOddsArray:
    """Clamp log-odds to OctoMap's ``[clamping_thres_min, clamping_thres_max]``.

    Clamping keeps every voxel able to change its mind after a bounded number of
    contrary observations.

    Parameters
    ----------
    log_odds : ndarray of float32, shape (m,)
        Log-odds after an update.
    ogm : OgmConfig
        Holds the thresholds as probabilities.

    Returns
    -------
    ndarray of float32, shape (m,)
    """
    low = np.float32(logodds(ogm.clamping_thres_min))
    high = np.float32(logodds(ogm.clamping_thres_max))
    return np.clip(log_odds, low, high)


def _sorted_unique(values: IntArray) -> IntArray:
    """Sorted unique values (np.unique's hash path is slow on shifted keys)."""
    v = np.sort(values)
    return v[np.r_[True, v[1:] != v[:-1]]] if v.size else v


def _batch_updates(batch: list[Scan], config: MapConfig) -> IntArray:
    """Compute one batch's update codes, sorted by voxel then scan (``computeUpdate``)."""
    res, depth = config.resolution, config.tree_depth
    sizes = [len(s) for s in batch]
    scan_id = np.repeat(np.arange(len(batch), dtype=np.int64), sizes)
    origins = np.repeat(np.stack([s.origin for s in batch]), sizes, axis=0)
    ends = np.concatenate([s.points for s in batch])
    max_range = np.repeat([np.inf if s.max_range is None else s.max_range for s in batch], sizes)

    # No-returns: a beam at least max_range long ends at max_range and has no hit.
    ray = ends - origins
    length = np.linalg.norm(ray, axis=1)
    no_return = length >= max_range
    ends[no_return] = (
        origins[no_return] + ray[no_return] * (max_range[no_return] / length[no_return])[:, None]
    )

    # Hits: one per voxel and scan.
    hit = ~no_return
    hit_keys = pack_keys(coord_to_key(ends[hit], res, depth))
    hits = _sorted_unique((hit_keys << (_SCAN_BITS + 1)) | (scan_id[hit] << 1) | 1)

    # Misses: traverse the beams in chunks of bounded size, one per voxel and scan.
    size = np.abs(ray).sum(axis=1) / res + config.dim  # upper bound on voxels per beam
    n_chunks = 1 + int(size.sum()) // _MAX_BATCH_VOXELS
    cuts = np.searchsorted(np.cumsum(size), np.arange(1, n_chunks) * float(_MAX_BATCH_VOXELS))
    frees = []
    for chunk in np.split(np.arange(len(ends)), np.unique(cuts)):
        beam, keys = traverse_voxels(origins[chunk], ends[chunk], res, depth)
        code = (pack_keys(keys) << (_SCAN_BITS + 1)) | (scan_id[chunk][beam] << 1)
        frees.append(_sorted_unique(code))
    free = _sorted_unique(np.concatenate(frees)) if len(frees) > 1 else frees[0]

    # Occupied wins: drop a miss where the same scan hits the same voxel.
    free = free[~sorted_contains(hits - 1, free)]
    return np.sort(np.concatenate([free, hits]))


def _apply_updates(
    keys: IntArray, log_odds: LogOddsArray, codes: IntArray, ogm: OgmConfig
) -> tuple[IntArray, LogOddsArray]:
    """Apply sorted update codes scan by scan (OctoMap's ``updateNodeLogOdds``)."""
    if codes.size == 0:
        return keys, log_odds
    voxel = codes >> (_SCAN_BITS + 1)
    delta = np.where(codes & 1, logodds(ogm.prob_hit), logodds(ogm.prob_miss)).astype(np.float32)
    first = np.flatnonzero(np.r_[True, voxel[1:] != voxel[:-1]])
    counts = np.diff(np.r_[first, voxel.size])
    touched = voxel[first]

    # New voxels enter the map unknown (log-odds 0), keeping the keys sorted.
    new = touched[~sorted_contains(keys, touched)]
    at = np.searchsorted(keys, new)
    keys = np.insert(keys, at, new)
    log_odds = np.insert(log_odds, at, np.float32(0.0))
    pos = np.searchsorted(keys, touched)

    # Update, then clamp, one scan at a time; voxels with most updates first so the
    # voxels still updating at round j are a prefix.
    order = np.argsort(-counts, kind="stable")
    first, counts, pos = first[order], counts[order], pos[order]
    active = np.searchsorted(-counts, -np.arange(int(counts[0])), side="left")
    for j, a in enumerate(active):
        p = pos[:a]
        log_odds[p] = clamp_log_odds(log_odds[p] + delta[first[:a] + j], ogm)
    return keys, log_odds


def build_ogm(scans: Iterable[Scan], config: MapConfig) -> OccupancyGridMap:
    """Build a log-odds occupancy grid from scans, as OctoMap's ``insertPointCloud``.

    Parameters
    ----------
    scans : iterable of Scan
        Scans in the world frame, in time order, of dimension ``config.dim``.
    config : MapConfig
        ``resolution``, ``tree_depth``, ``dim`` and the sensor model ``ogm``.

    Returns
    -------
    OccupancyGridMap

    Raises
    ------
    OctolgpError
        On a non-Scan item, a scan of the wrong dimension, or a point outside the
        addressable range.
    """
    if not isinstance(config, MapConfig):
        raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
    keys = np.empty(0, dtype=np.int64)
    log_odds = np.empty(0, dtype=np.float32)
    batch: list[Scan] = []
    load = 0.0
    for i, scan in enumerate(scans):
        if not isinstance(scan, Scan) or scan.dim != config.dim:
            raise OctolgpError(f"scans[{i}] must be a {config.dim}D Scan (MapConfig.dim)")
        ends_and_origin = np.vstack([scan.points, scan.origin])
        if not addressable_mask(ends_and_origin, config.resolution, config.tree_depth).all():
            low, high = addressable_range(config.resolution, config.tree_depth)
            raise OctolgpError(
                f"scans[{i}]: Scan.points or Scan.origin outside [{low:g}, {high:g}) m"
            )
        batch.append(scan)
        load += float(np.abs(scan.points - scan.origin).sum()) / config.resolution
        if load >= _MAX_BATCH_VOXELS or len(batch) == _MAX_BATCH_SCANS:
            keys, log_odds = _apply_updates(
                keys, log_odds, _batch_updates(batch, config), config.ogm
            )
            batch, load = [], 0.0
    if batch:
        keys, log_odds = _apply_updates(keys, log_odds, _batch_updates(batch, config), config.ogm)
    return OccupancyGridMap(keys, log_odds, config)


class OccupancyGridMap:
    """A sparse log-odds occupancy grid over OctoMap keys.

    Only observed voxels are stored; every other point is unknown: probability
    exactly 0.5, log-odds 0. The grid has no variance. Points outside the
    addressable range (:func:`~octolgp.geometry.keys.addressable_range`) are unknown.

    Every query takes ``points``, an array_like of shape ``(q, dim)`` in the world
    frame, metres, and raises :class:`~octolgp.errors.OctolgpError` naming
    ``points`` on a bad shape, a wrong dimension or a non-finite value.

    Parameters
    ----------
    keys : ndarray of int64, shape (m,)
        Packed OctoMap keys of the known voxels, sorted, unique.
    log_odds : ndarray of float32, shape (m,)
        Their log-odds.
    config : MapConfig
        ``resolution``, ``tree_depth`` and ``dim`` of the keys.
    """

    def __init__(self, keys: IntArray, log_odds: LogOddsArray, config: MapConfig) -> None:
        keys = np.asarray(keys, dtype=np.int64)
        log_odds = np.asarray(log_odds, dtype=np.float32)
        if keys.ndim != 1 or keys.shape != log_odds.shape:
            raise OctolgpError(f"keys {keys.shape} and log_odds {log_odds.shape} must be (m,)")
        if keys.size > 1 and not (np.diff(keys) > 0).all():
            raise OctolgpError("keys must be sorted and unique")
        self._keys, self._log_odds, self.config = keys, log_odds, config
        self._keys.setflags(write=False)
        self._log_odds.setflags(write=False)

    @property
    def n_voxels(self) -> int:
        """Number of known voxels."""
        return int(self._keys.size)

    @property
    def dim(self) -> int:
        """Spatial dimension, 2 or 3."""
        return self.config.dim

    @property
    def keys(self) -> IntArray:
        """Packed keys of the known voxels, sorted, shape (m,), read-only."""
        return self._keys

    @property
    def log_odds(self) -> LogOddsArray:
        """Log-odds of the known voxels, shape (m,), read-only."""
        return self._log_odds

    def voxel_centres(self) -> FloatArray:
        """Return the known voxels' centres, shape (m, dim), world frame, metres."""
        keys = unpack_keys(self._keys, self.dim)
        return key_to_coord(keys, self.config.resolution, self.config.tree_depth)

    def _lookup(self, points: ArrayLike) -> tuple[IntArray, NDArray[np.bool_]]:
        """Return each query's row in the store and whether it is known."""
        pts = as_points(points, "points", dim=self.dim)
        res, depth = self.config.resolution, self.config.tree_depth
        inside = addressable_mask(pts, res, depth)
        packed = np.full(pts.shape[0], -1, dtype=np.int64)
        packed[inside] = pack_keys(coord_to_key(pts[inside], res, depth))
        if self.n_voxels == 0:
            return packed, np.zeros(pts.shape[0], dtype=bool)
        row = np.minimum(np.searchsorted(self._keys, packed), self.n_voxels - 1)
        return row, inside & (self._keys[row] == packed)

    def known_mask(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Return whether each point lies in an observed voxel, shape (q,)."""
        return self._lookup(points)[1]

    def log_odds_at(self, points: ArrayLike) -> FloatArray:
        """Return the log-odds at each point, 0 where unknown, float64 of shape (q,)."""
        row, known = self._lookup(points)
        out = np.zeros(row.shape[0], dtype=np.float64)
        out[known] = self._log_odds[row[known]]
        return out

    def occupancy(self, points: ArrayLike) -> FloatArray:
        """Return ``p(occupied) = 1 / (1 + exp(-log_odds))``, float64 of shape (q,).

        Exactly 0.5 where unknown.
        """
        return 1.0 / (1.0 + np.exp(-self.log_odds_at(points)))

    def latent(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return the latent mean and variance, as the GP maps do.

        Returns
        -------
        mean : ndarray of float64, shape (q,)
            The log-odds, 0 where unknown.
        var : ndarray of float64, shape (q,)
            Zeros: a grid carries no uncertainty about its own estimate.
        """
        mean = self.log_odds_at(points)
        return mean, np.zeros_like(mean)
