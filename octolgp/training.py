"""Scan → training data: a hit point (target +1) and a free segment (target −1) per beam.

The free segment runs from the sensor to ``free_margin`` metres short of the hit
(one resolution by default) so that it does not cancel the hit. A no-return beam
(length >= ``Scan.max_range``) gives a free segment to ``max_range`` and no hit.
Segment targets follow the *average* formulation of the integral kernel (see
:mod:`octolgp.gp.kernels`): the mean of the latent function along a free segment is −1.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.scan import NO_RETURN_RTOL, FloatArray, Scan

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class TrainingData:
    """Hits and free segments in the world frame.

    Attributes
    ----------
    hits : ndarray of shape (h, d)
        Hit points, metres. Target +1.
    seg_start, seg_end : ndarray of shape (s, d)
        Free segments, metres. Target −1 (mean of the latent along the segment).
    seg_hit : ndarray of shape (s,)
        Index into ``hits`` of the hit that ends each segment's beam, −1 for a
        no-return.
    """

    hits: FloatArray
    seg_start: FloatArray
    seg_end: FloatArray
    seg_hit: IntArray

    @property
    def dim(self) -> int:
        """Spatial dimension."""
        return int(self.hits.shape[1])

    @property
    def n_items(self) -> int:
        """Number of training items (hits plus segments)."""
        return int(self.hits.shape[0] + self.seg_start.shape[0])


def check_scans(scans: Iterable[Scan], dim: int) -> list[Scan]:
    """Materialise and type-check scans against the map dimension.

    Raises
    ------
    OctolgpError
        If an item is not a :class:`Scan`, the dimensions differ from ``dim`` or
        there are no scans.
    """
    out: list[Scan] = [scans] if isinstance(scans, Scan) else list(scans)
    if not out:
        raise OctolgpError("scans is empty: need at least one Scan")
    for i, scan in enumerate(out):
        if not isinstance(scan, Scan):
            raise OctolgpError(f"scans[{i}] must be a Scan, got {type(scan).__name__}")
        if scan.dim != dim:
            raise OctolgpError(f"scans[{i}] is {scan.dim}D but MapConfig.dim is {dim}")
    return out


def stack_beams(scan_list: list[Scan]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Every beam of the scans, stacked.

    Returns
    -------
    origins, ends : ndarray of shape (b, d)
        Sensor position and endpoint of each beam, world frame, metres.
    max_range : ndarray of shape (b,)
        The beam's scan's no-return range (``inf`` where the scan has none).
    """
    counts = np.array([len(s) for s in scan_list])
    origins = np.repeat(np.stack([s.origin for s in scan_list]), counts, axis=0)
    ends = np.concatenate([s.points for s in scan_list])
    max_range = np.repeat(
        np.array([np.inf if s.max_range is None else s.max_range for s in scan_list]), counts
    )
    return origins, ends, max_range


def _first_per_voxel(points: FloatArray, resolution: float) -> tuple[IntArray, IntArray]:
    """Indices of the first point in each voxel, and each point's kept index."""
    keys = np.floor(points / resolution).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # keep original (time) order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order].astype(np.int64), rank[inverse.ravel()].astype(np.int64)


@dataclass(frozen=True)
class Beams:
    """Each beam split into its free segment and its hit (the rule of this module).

    Attributes
    ----------
    length : ndarray of shape (b,)
        Beam length, metres.
    is_hit : ndarray of bool, shape (b,)
        The beam ends in a return (not a no-return, not of zero length).
    has_seg : ndarray of bool, shape (b,)
        The beam has a free segment of positive length.
    free_end : ndarray of shape (b, d)
        End of the free segment (``free_margin`` short of the hit, or at
        ``max_range`` for a no-return), metres, world frame.
    """

    length: FloatArray
    is_hit: NDArray[np.bool_]
    has_seg: NDArray[np.bool_]
    free_end: FloatArray


def split_beams(
    origins: FloatArray,
    ends: FloatArray,
    max_range: FloatArray,
    free_margin: float,
    free_range: float = math.inf,
    no_return_range: float = math.inf,
) -> Beams:
    """Split beams into free segments and hits.

    Parameters
    ----------
    origins, ends : ndarray of shape (b, d)
        Sensor position and endpoint of each beam, world frame, metres.
    max_range : ndarray of shape (b,)
        No-return range of each beam (``inf`` for none).
    free_margin : float
        Metres a free segment stops short of its hit.
    free_range : float
        Metres from the sensor a beam's evidence reaches (OctoMap's ``maxrange``): a
        no-return is free up to it, a return beyond it is free up to it and loses its
        hit. ``inf``: every beam whole.
    no_return_range : float
        Metres a no-return beam is free up to (at most ``free_range``).
    """
    vec = ends - origins
    length = np.linalg.norm(vec, axis=1)
    valid, no_return, truncated, free_len = free_lengths(
        length, max_range, free_margin, free_range, no_return_range
    )
    is_hit = valid & ~no_return & ~truncated
    direction = np.divide(vec, length[:, None], out=np.zeros_like(vec), where=valid[:, None])
    has_seg = valid & (free_len > 1e-9)
    free_end = origins + direction * np.maximum(free_len, 0.0)[:, None]
    return Beams(length, is_hit, has_seg, free_end)


def free_lengths(
    length: FloatArray,
    max_range: FloatArray,
    free_margin: float,
    free_range: float = math.inf,
    no_return_range: float = math.inf,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_], FloatArray]:
    """Each beam's kind and free-segment length (:func:`split_beams`'s rule).

    Parameters
    ----------
    length : ndarray of shape (b,)
        Each beam's length, metres.
    max_range, free_margin, free_range, no_return_range
        As :func:`split_beams` takes them.

    Returns
    -------
    valid, no_return, truncated : ndarray of bool, shape (b,)
        The beam has a direction; it is a no-return; it is a return beyond
        ``free_range``.
    free_len : ndarray of shape (b,)
        Its free segment's length (``<= 0``: none).
    """
    valid = length > 1e-9  # an endpoint on the sensor carries no direction
    # relative tolerance: a range reported at exactly max_range must not round into a hit
    no_return = valid & (length >= max_range * (1.0 - NO_RETURN_RTOL))
    truncated = valid & ~no_return & (length > free_range)
    # Free segment: to max_range for no-returns, else stop free_margin short of the hit;
    # no farther than free_range.
    reach = np.minimum(np.minimum(length, max_range), no_return_range)
    free_len = np.where(no_return, reach, length - free_margin)
    free_len = np.where(truncated, free_range, np.minimum(free_len, free_range))
    return valid, no_return, truncated, free_len


def config_beams(
    origins: FloatArray, ends: FloatArray, max_range: FloatArray, config: MapConfig
) -> Beams:
    """:func:`split_beams` with the sensor model of ``config`` (its margin and ranges)."""
    return split_beams(
        origins, ends, max_range, config.free_margin, config.free_range, config.no_return_range
    )


def make_training_data(scans: Iterable[Scan], config: MapConfig) -> TrainingData:
    """Turn scans into hits and free segments, deduplicated per voxel and class.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim``.
    config : MapConfig
        Uses ``resolution``, ``free_margin`` and ``training.dedup``.

    Returns
    -------
    TrainingData

    Raises
    ------
    OctolgpError
        On an empty sequence or a dimension mismatch.
    """
    scan_list = check_scans(scans, config.dim)
    origins, ends, max_range = stack_beams(scan_list)
    beams = config_beams(origins, ends, max_range, config)
    is_hit, has_seg = beams.is_hit, beams.has_seg
    length = beams.length
    hit_index = np.full(length.shape, -1, dtype=np.int64)
    hit_index[is_hit] = np.arange(int(is_hit.sum()))
    hits = ends[is_hit]
    seg_start = origins[has_seg]
    seg_end = beams.free_end[has_seg]
    seg_hit = hit_index[has_seg]

    if config.training.dedup:
        # Balance the classes: one hit per voxel, one segment per voxel of its end.
        if hits.shape[0]:
            keep_hit, hit_rank = _first_per_voxel(hits, config.resolution)
            hits = hits[keep_hit]
            seg_hit = np.where(seg_hit >= 0, hit_rank[np.maximum(seg_hit, 0)], -1)
        if seg_end.shape[0]:
            keep_seg, _ = _first_per_voxel(seg_end, config.resolution)
            seg_start, seg_end, seg_hit = seg_start[keep_seg], seg_end[keep_seg], seg_hit[keep_seg]
    return TrainingData(
        hits=np.ascontiguousarray(hits, dtype=np.float64),
        seg_start=np.ascontiguousarray(seg_start, dtype=np.float64),
        seg_end=np.ascontiguousarray(seg_end, dtype=np.float64),
        seg_hit=seg_hit.astype(np.int64),
    )
