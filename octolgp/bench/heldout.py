"""Held-out-scan evaluation for real logs, where no ground-truth map exists.

Protocol
--------
1. :func:`heldout_split` holds out about ``fraction`` of a log's scans, in
   contiguous runs, so that a test scan's neighbours in time are held out with it
   and the map cannot simply copy a nearly identical training scan.
2. The map is built from the training scans only.
3. :func:`heldout_points` turns the held-out beams into labelled test points:
   every real return's endpoint is occupied (1), and points sampled along each
   beam, stopping ``short`` metres before the hit, are free (0).
4. :func:`evaluate` scores the map's ``P(occupied)`` at those points by ROC AUC,
   and reports which fraction of them the map leaves unknown (exactly 0.5).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.metrics import roc_auc_score

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.scan import NO_RETURN_RTOL, Scan, as_points
from octolgp.training import stack_beams

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
LabelArray = NDArray[np.int8]


MIN_BEAM_LENGTH = 1e-9
"""Beams this short (metres) carry no direction and give no test points."""


class OccupancyMap(Protocol):
    """Anything with ``occupancy(points) -> P(occupied)``: every map and reference peer."""

    def occupancy(self, points: FloatArray) -> FloatArray:
        """Return ``P(occupied)`` of shape ``(q,)`` at ``points`` of shape ``(q, d)``."""
        ...


def _check_int(value: object, name: str, low: int) -> int:
    """Return ``value`` as an int, raising unless it is an integer ``>= low``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise OctolgpError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def _check_float(value: object, name: str, low: float, high: float = math.inf) -> float:
    """Return ``value`` as a float, raising unless it is finite and in ``[low, high]``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float | np.integer | np.floating)
        or not math.isfinite(value)
        or not low <= value <= high
    ):
        raise OctolgpError(f"{name} must be a finite number in [{low}, {high}], got {value!r}")
    return float(value)


def heldout_split(
    n_scans: int, fraction: float = 0.1, run: int = 40, seed: int = 0
) -> tuple[IntArray, IntArray]:
    """Split scan indices into training and held-out test scans, in contiguous runs.

    ``n_test = round(fraction * n_scans)`` scans are held out (at least one, and at
    least one scan is left for training). They form ``ceil(n_test / run)``
    non-overlapping runs of consecutive scans whose lengths differ by at most one
    and are at most ``run``: when ``n_test`` is a multiple of ``run`` every run is
    exactly ``run`` long, and a log too short for one full run gets a single,
    shorter run of ``n_test`` scans. The held-out fraction is therefore as close to
    ``fraction`` as whole scans allow.

    The runs are placed uniformly at random among all non-overlapping placements
    (stars and bars: ``n_runs`` sorted distinct draws from
    ``range(n_scans - n_test + n_runs)``, the ``i``-th shifted by the lengths of the
    runs before it). Runs may touch, and then read as one longer run.

    Parameters
    ----------
    n_scans : int
        Scans in the log, ``>= 2``.
    fraction : float, optional
        Share of the scans to hold out, in ``(0, 1)``.
    run : int, optional
        Longest run of consecutive held-out scans, ``>= 1``.
    seed : int, optional
        Seed of the placement; the same arguments give the same split.

    Returns
    -------
    train_idx : ndarray of int64, shape (n_scans - n_test,)
        Sorted training scan indices.
    test_idx : ndarray of int64, shape (n_test,)
        Sorted held-out scan indices; with ``train_idx`` a partition of
        ``range(n_scans)``.

    Raises
    ------
    OctolgpError
        On ``n_scans < 2``, ``fraction`` outside ``(0, 1)`` or ``run < 1``.
    """
    n = _check_int(n_scans, "heldout_split: n_scans", 2)
    frac = _check_float(fraction, "heldout_split: fraction", 0.0, 1.0)
    if frac in (0.0, 1.0):
        raise OctolgpError(f"heldout_split: fraction must be in (0, 1), got {fraction!r}")
    max_run = _check_int(run, "heldout_split: run", 1)
    rng = np.random.default_rng(seed)

    n_test = min(max(round(frac * n), 1), n - 1)
    n_runs = -(-n_test // max_run)
    # Run lengths: n_test split as evenly as possible, each <= run, in random order.
    lengths = np.full(n_runs, n_test // n_runs, dtype=np.int64)
    lengths[: n_test % n_runs] += 1
    lengths = rng.permutation(lengths)
    # Stars and bars: n_runs slots among the n - n_test training scans.
    slots = np.sort(rng.choice(n - n_test + n_runs, size=n_runs, replace=False)).astype(np.int64)
    before = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    starts = slots - np.arange(n_runs, dtype=np.int64) + before
    # Each run's scans: its start repeated, plus the offset within the run.
    test_idx = np.repeat(starts, lengths) + (
        np.arange(n_test, dtype=np.int64) - np.repeat(before, lengths)
    )
    held = np.zeros(n, dtype=bool)
    held[test_idx] = True
    return np.flatnonzero(~held).astype(np.int64), np.flatnonzero(held).astype(np.int64)


def _one_dimension(scans: Sequence[Scan], who: str) -> list[Scan]:
    """The scans as a list; at least one, all of one dimension (else ``OctolgpError``)."""
    scan_list = list(scans)
    if not scan_list:
        raise OctolgpError(f"{who}: no scans")
    dims = {s.dim for s in scan_list}
    if len(dims) != 1:
        raise OctolgpError(f"{who}: scans of mixed dimension {sorted(dims)}")
    return scan_list


def _labelled(
    origin: FloatArray,
    end: FloatArray,
    delta: FloatArray,
    length: FloatArray,
    hit: NDArray[np.bool_],
    per_beam: NDArray[np.integer],
    free_len: FloatArray,
    generator: np.random.Generator,
) -> tuple[FloatArray, LabelArray]:
    """Endpoints of ``hit`` beams (occupied), then ``per_beam`` free points per beam.

    The free points of beam ``b`` are ``origin + t * direction`` with ``t`` uniform on
    ``[0, free_len[b])``, drawn in beam order; ``delta = end - origin`` and ``length``
    its norm, per beam.
    """
    beam = np.repeat(np.arange(length.size), per_beam)
    t = generator.random(beam.size) * free_len[beam]
    free_points = origin[beam] + (t / length[beam])[:, None] * delta[beam]
    points = np.concatenate([end[hit], free_points])
    labels = np.concatenate(
        [np.ones(int(hit.sum()), dtype=np.int8), np.zeros(beam.size, dtype=np.int8)]
    )
    return points, labels


def heldout_points(
    scans: Sequence[Scan],
    rng: np.random.Generator | int,
    free_per_beam: int = 1,
    short: float = 0.1,
    resolution: float | None = None,
) -> tuple[FloatArray, LabelArray]:
    """Labelled test points from held-out scans: hits occupied, beam samples free.

    A beam is a real return when ``MIN_BEAM_LENGTH < length < max_range * (1 -
    NO_RETURN_RTOL)`` (any length above ``MIN_BEAM_LENGTH`` when the scan has no
    ``max_range``); its endpoint is an occupied point, and its free segment runs from
    the origin to ``margin = max(short, resolution)`` metres before the hit. A
    no-return beam gives no occupied point and a free segment to ``max_range``.
    Each free segment longer than ``MIN_BEAM_LENGTH`` gets ``free_per_beam`` points
    drawn uniformly on ``origin + t * direction`` with ``0 <= t < segment length``,
    so every free point lies strictly before the segment's end.

    Parameters
    ----------
    scans : sequence of Scan
        The held-out scans, all of one dimension ``d``; world frame.
    rng : numpy.random.Generator or int
        Source (or seed) of the free samples.
    free_per_beam : int, optional
        Free points per beam, ``>= 0``.
    short : float, optional
        Gap between the last free point and the hit, metres, ``>= 0``. It keeps
        free points out of the wall's own surface, where a hit and a free label
        would contradict each other.
    resolution : float, optional
        Voxel edge of the maps under test, metres. When given the gap is at least
        one voxel, so no free point shares the hit's voxel (the margin that the
        training data uses between a free segment and its hit).

    Returns
    -------
    points : ndarray of shape (m, d)
        Test points in the world frame, metres: all occupied points first, in
        beam order, then all free points, in beam order.
    labels : ndarray of int8, shape (m,)
        1 occupied, 0 free.

    Raises
    ------
    OctolgpError
        On no scans, scans of mixed dimension, ``free_per_beam < 0``, or a negative
        or non-finite ``short`` or ``resolution``.
    """
    scan_list = _one_dimension(scans, "heldout_points")
    per_free = _check_int(free_per_beam, "heldout_points: free_per_beam", 0)
    margin = _check_float(short, "heldout_points: short", 0.0)
    if resolution is not None:
        margin = max(margin, _check_float(resolution, "heldout_points: resolution", 0.0))
    generator = np.random.default_rng(rng)

    # Beams of all scans, stacked: origin, endpoint and max_range per beam.
    origin, end, max_range = stack_beams(scan_list)
    delta = end - origin
    length = np.linalg.norm(delta, axis=1)

    # Classify: real return (hit) or no-return; beams on the sensor are dropped.
    valid = length > MIN_BEAM_LENGTH
    no_return = valid & (length >= max_range * (1.0 - NO_RETURN_RTOL))
    hit = valid & ~no_return
    free_len = np.where(no_return, np.minimum(length, max_range), length - margin)
    has_free = valid & (free_len > MIN_BEAM_LENGTH)

    # Free samples: free_per_beam per segment, t ~ U[0, free_len) along the unit direction.
    per_beam = np.where(has_free, per_free, 0)
    return _labelled(origin, end, delta, length, hit, per_beam, free_len, generator)


def hilbert_points(
    scans: Sequence[Scan], rng: np.random.Generator | int, short: float = 0.1
) -> tuple[FloatArray, LabelArray]:
    """Labelled test points as Hilbert maps' reference code makes them.

    Every held-out beam with a return gives its endpoint (occupied) and ``max(1,
    int(d / 2))`` points drawn uniformly on ``[0, d - short]`` metres along it (free),
    ``d`` the beam's length; no-return beams give nothing. The protocol of the
    published Hilbert-map figures, which weighs long beams more than
    :func:`heldout_points` does.

    Parameters
    ----------
    scans : sequence of Scan
        The held-out scans, all of one dimension; world frame.
    rng : numpy.random.Generator or int
        Source (or seed) of the free samples.
    short : float, optional
        Metres kept free before each return, ``>= 0``.

    Returns
    -------
    points : ndarray of shape (m, d)
        Occupied endpoints first (beam order), then free points (beam order), metres.
    labels : ndarray of int8, shape (m,)
        1 occupied, 0 free.

    Raises
    ------
    OctolgpError
        On no scans, scans of mixed dimension, or a negative or non-finite ``short``.
    """
    scan_list = _one_dimension(scans, "hilbert_points")
    margin = _check_float(short, "hilbert_points: short", 0.0)
    generator = np.random.default_rng(rng)
    origin, end, max_range = stack_beams(scan_list)
    delta = end - origin
    length = np.linalg.norm(delta, axis=1)
    hit = (length > MIN_BEAM_LENGTH) & (length < max_range * (1.0 - NO_RETURN_RTOL))
    free_len = np.maximum(length - margin, 0.0)
    # int(d / 2), robust to the range a point's norm gives back (6.0 -> 5.999...)
    per_beam = np.where(hit, np.maximum(1, np.floor(length / 2.0 + 1e-9).astype(np.int64)), 0)
    return _labelled(origin, end, delta, length, hit, per_beam, free_len, generator)


def _novel_mask(train: list[Scan], pts: FloatArray, radius: float) -> np.ndarray:
    """Which of ``pts`` (m, d) have no training return within ``radius`` metres."""
    from scipy.spatial import cKDTree

    origin, end, max_range = stack_beams(train)
    length = np.linalg.norm(end - origin, axis=1)
    returns = end[(length > MIN_BEAM_LENGTH) & (length < max_range * (1.0 - NO_RETURN_RTOL))]
    if returns.shape[0] == 0:
        return np.ones(pts.shape[0], dtype=bool)
    dist, _ = cKDTree(returns).query(pts, distance_upper_bound=radius)
    out: np.ndarray = ~(dist <= radius)
    return out


def novel_fraction(train: Sequence[Scan], points: ArrayLike, radius: float) -> float:
    """Share of ``points`` with no training return within ``radius`` metres.

    A property of a split, not of a method: for the occupied test points it measures how
    much of what the held-out scans hit the training scans never hit (walls seen only
    from the held-out stretch of the path), which no map built from the training
    scans can be expected to read as occupied.

    Parameters
    ----------
    train : sequence of Scan
        The training scans; world frame.
    points : array_like of shape (m, d)
        Query points (metres, world frame).
    radius : float
        Metres, ``> 0``.

    Returns
    -------
    float
        In [0, 1]; 0 for no points, 1 when the training scans have no return at all.
    """
    pts = as_points(points, "novel_fraction: points")
    if pts.shape[0] == 0:
        return 0.0
    return float(np.mean(_novel_mask(_one_dimension(train, "novel_fraction"), pts, radius)))


def seen_free_fraction(
    train: Sequence[Scan], points: ArrayLike, radius: float, config: MapConfig
) -> float:
    """Share of ``points`` far from every training return but in voxels it saw free.

    Counts the points with no training return within ``radius`` metres whose voxel a
    training beam's free segment crossed. For the occupied test points: held-out returns
    where the training scans looked through and saw nothing, so the scans contradict each
    other there (a pose error between the two stretches of the path, something that
    moved, glass); the rest of the novel points (:func:`novel_fraction`) lie where the
    training scans never looked. Free segments as the map's
    (:func:`octolgp.observations.observe`, static counts).

    Parameters
    ----------
    train : sequence of Scan
        The training scans; world frame.
    points : array_like of shape (m, d)
        Query points (metres, world frame).
    radius : float
        Metres, ``> 0``.
    config : MapConfig
        Uses ``dim``, ``resolution``, ``tree_depth`` and ``free_margin``.

    Returns
    -------
    float
        In [0, :func:`novel_fraction`]; 0 for no points.
    """
    from octolgp.geometry.keys import coord_to_key, pack_keys
    from octolgp.observations import observe

    pts = as_points(points, "seen_free_fraction: points")
    if pts.shape[0] == 0:
        return 0.0
    scans = _one_dimension(train, "seen_free_fraction")
    novel = _novel_mask(scans, pts, radius)
    static = dataclasses.replace(config, online=dataclasses.replace(config.online, clear_scans=0))
    obs = observe(scans, static)
    seen_free = np.sort(pack_keys(obs.keys[obs.frees > 0]))
    packed = pack_keys(coord_to_key(pts[novel], config.resolution, config.tree_depth))
    if seen_free.size == 0:
        return 0.0
    at = np.minimum(np.searchsorted(seen_free, packed), seen_free.size - 1)
    crossed = int(np.count_nonzero(seen_free[at] == packed))
    return crossed / len(pts)


PROTOCOLS = ("endpoint", "hilbert")
"""Test-point protocols of ``octolgp eval``: :func:`heldout_points` (one free point per
beam) and :func:`hilbert_points`."""


def auc(labels: ArrayLike, scores: ArrayLike) -> float:
    """Area under the ROC curve of ``scores`` against binary ``labels``.

    Parameters
    ----------
    labels : array_like of shape (m,)
        1 occupied, 0 free.
    scores : array_like of shape (m,)
        Higher means more likely occupied, for example ``P(occupied)``; ties
        (such as unknown cells at 0.5) count half.

    Returns
    -------
    float
        ROC AUC in ``[0, 1]``; 1 for a perfect ranking, 0.5 for chance.

    Raises
    ------
    OctolgpError
        On mismatched or non-1D shapes, labels other than 0 and 1, a single class,
        or non-finite scores.
    """
    y = np.asarray(labels)
    s = np.asarray(scores, dtype=np.float64)
    if y.ndim != 1 or s.shape != y.shape:
        raise OctolgpError(f"auc: labels {y.shape} and scores {s.shape} must be equal 1D shapes")
    if not np.isin(y, (0, 1)).all():
        raise OctolgpError("auc: labels must be 0 (free) or 1 (occupied)")
    if np.unique(y).size != 2:
        raise OctolgpError("auc: labels need both classes, occupied and free")
    if not np.isfinite(s).all():
        raise OctolgpError("auc: scores contain NaN or inf")
    return float(roc_auc_score(y, s))


def unknown_fraction(probs: ArrayLike) -> float:
    """Fraction of probabilities exactly 0.5: the cells a map leaves unknown.

    Parameters
    ----------
    probs : array_like of shape (m,)
        ``P(occupied)`` at the test points.

    Returns
    -------
    float
        In ``[0, 1]``.

    Raises
    ------
    OctolgpError
        On an empty or non-1D array.
    """
    p = np.asarray(probs, dtype=np.float64)
    if p.ndim != 1 or p.size == 0:
        raise OctolgpError(f"unknown_fraction: probs must be a non-empty 1D array, got {p.shape}")
    return float(np.mean(p == 0.5))


def evaluate(map_obj: OccupancyMap, points: ArrayLike, labels: ArrayLike) -> dict[str, float | int]:
    """Score a map on held-out test points.

    Parameters
    ----------
    map_obj : OccupancyMap
        Anything with ``occupancy(points) -> ndarray (q,)``: a ``GPMap``, the OGM,
        or :class:`~octolgp.bench.octomap_ref.OctomapReference`.
    points : array_like of shape (m, d)
        Test points in the world frame, metres (from :func:`heldout_points`).
    labels : array_like of shape (m,)
        1 occupied, 0 free.

    Returns
    -------
    dict
        ``auc``: ROC AUC over all points, unknowns scored 0.5;
        ``auc_known``: ROC AUC over the points the map knows (``nan`` when those
        lack a class); ``unknown_fraction``; ``n_points``; ``n_occupied``.

    Raises
    ------
    OctolgpError
        On invalid points or labels (see :func:`auc`).
    """
    X = as_points(points, "evaluate: points")
    y = np.asarray(labels)
    if y.shape != (X.shape[0],):
        raise OctolgpError(f"evaluate: labels {y.shape} must have shape ({X.shape[0]},)")
    probs = np.asarray(map_obj.occupancy(X), dtype=np.float64)
    known = probs != 0.5
    y_known = y[known]
    return {
        "auc": auc(y, probs),
        "auc_known": auc(y_known, probs[known]) if np.unique(y_known).size == 2 else math.nan,
        "unknown_fraction": unknown_fraction(probs),
        "n_points": int(y.size),
        "n_occupied": int(np.count_nonzero(y == 1)),
    }
