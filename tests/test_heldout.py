"""Held-out-scan protocol: the split partitions the log, test points lie on their beams."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.bench.heldout import (
    auc,
    evaluate,
    heldout_points,
    heldout_split,
    hilbert_points,
    unknown_fraction,
)
from octolgp.errors import OctolgpError
from octolgp.scan import Scan

# --- heldout_split -------------------------------------------------------------------


def _runs(idx: np.ndarray) -> list[int]:
    """Lengths of the maximal runs of consecutive integers in sorted ``idx``."""
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    return [len(r) for r in np.split(idx, breaks)]


@given(
    n=st.integers(2, 3000),
    fraction=st.floats(0.01, 0.6),
    run=st.integers(1, 60),
    seed=st.integers(0, 2**32 - 1),
)
def test_split_partitions_indices(n: int, fraction: float, run: int, seed: int) -> None:
    train, test = heldout_split(n, fraction, run, seed)
    assert train.dtype == np.int64
    assert test.dtype == np.int64
    assert np.all(np.diff(train) > 0)
    assert np.all(np.diff(test) > 0)
    np.testing.assert_array_equal(np.sort(np.concatenate([train, test])), np.arange(n))
    assert train.size >= 1
    assert test.size == min(max(round(fraction * n), 1), n - 1)


@given(
    n=st.integers(2, 3000),
    fraction=st.floats(0.01, 0.6),
    run=st.integers(1, 60),
    seed=st.integers(0, 2**32 - 1),
)
def test_split_runs_are_contiguous_and_short(n: int, fraction: float, run: int, seed: int) -> None:
    _, test = heldout_split(n, fraction, run, seed)
    n_runs = math.ceil(test.size / run)
    lengths = _runs(test)
    # Touching runs merge, so the maximal runs are at most n_runs and sum to n_test.
    assert len(lengths) <= n_runs
    assert sum(lengths) == test.size
    # Every maximal run is a union of whole runs of near-equal length <= run.
    low = test.size // n_runs
    assert all(length >= low for length in lengths)


def test_split_exact_runs_when_multiple() -> None:
    # 1000 scans, 10 %, runs of 20: 100 held out in 5 runs of exactly 20.
    train, test = heldout_split(1000, fraction=0.1, run=20, seed=3)
    assert test.size == 100
    assert train.size == 900
    lengths = _runs(test)
    assert all(length % 20 == 0 for length in lengths)


def test_split_fraction_and_run_lengths() -> None:
    # 2000 scans, 10 %, runs of 40: 200 held out in 5 runs of exactly 40.
    _, test = heldout_split(2000, fraction=0.1, run=40, seed=0)
    assert test.size == 200
    assert all(length % 40 == 0 for length in _runs(test))


def test_split_short_log_shrinks_run() -> None:
    # 50 scans, 10 %, runs of 40: a single run of 5.
    train, test = heldout_split(50, fraction=0.1, run=40, seed=1)
    assert test.size == 5
    assert _runs(test) == [5]
    assert train.size == 45


def test_split_is_seeded() -> None:
    a = heldout_split(910, 0.1, 40, seed=7)
    b = heldout_split(910, 0.1, 40, seed=7)
    c = heldout_split(910, 0.1, 40, seed=8)
    np.testing.assert_array_equal(a[1], b[1])
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.array_equal(a[1], c[1])


def test_split_places_runs_everywhere() -> None:
    # Uniform placement: over many seeds every scan is held out at some point.
    held = np.zeros(100, dtype=int)
    for seed in range(400):
        held[heldout_split(100, 0.1, 5, seed)[1]] += 1
    assert held.min() > 0
    # Each seed holds out 10 of 100 scans.
    assert held.sum() == 400 * 10


@pytest.mark.parametrize(
    ("n", "fraction", "run"),
    [(1, 0.1, 40), (10, 0.0, 40), (10, 1.0, 40), (10, -0.1, 4), (10, 0.1, 0), (10, math.nan, 4)],
)
def test_split_rejects_bad_arguments(n: int, fraction: float, run: int) -> None:
    with pytest.raises(OctolgpError):
        heldout_split(n, fraction, run)


# --- heldout_points ------------------------------------------------------------------


def _random_scan(rng: np.random.Generator, dim: int, n: int, max_range: float | None) -> Scan:
    origin = rng.uniform(-5, 5, size=dim)
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0.05, 12.0, size=(n, 1))
    return Scan(origin, origin + length * direction, max_range=max_range)


def _free_on_beams(scans: list[Scan], free: np.ndarray, margin: float) -> None:
    """Every free point lies on some beam, before its free segment's end."""
    ok = np.zeros(len(free), dtype=bool)
    for scan in scans:
        d = scan.points - scan.origin
        length = np.linalg.norm(d, axis=1)
        u = d / length[:, None]
        rel = free[:, None, :] - scan.origin  # (m, 1, dim)
        t = np.einsum("mnd,nd->mn", np.broadcast_to(rel, (len(free), len(d), d.shape[1])), u)
        off = np.linalg.norm(rel - t[:, :, None] * u[None, :, :], axis=2)
        mr = np.inf if scan.max_range is None else scan.max_range
        no_return = length >= mr * (1 - 1e-9)
        end = np.where(no_return, np.minimum(length, mr), length - margin)
        on = (off < 1e-9) & (t >= 0) & (t < end)
        ok |= on.any(axis=1)
    assert ok.all()


@pytest.mark.parametrize("dim", [2, 3])
def test_points_hits_and_free_segments(dim: int) -> None:
    rng = np.random.default_rng(0)
    scans = [_random_scan(rng, dim, 30, max_range=None) for _ in range(3)]
    points, labels = heldout_points(scans, rng=1, free_per_beam=4, short=0.2)
    assert points.shape[1] == dim
    assert labels.dtype == np.int8
    lengths = np.concatenate([np.linalg.norm(s.points - s.origin, axis=1) for s in scans])
    n_hits = 90
    n_free = 4 * int(np.count_nonzero(lengths - 0.2 > 1e-9))
    assert np.count_nonzero(labels == 1) == n_hits
    assert np.count_nonzero(labels == 0) == n_free
    # Hits are the endpoints, in beam order; free points follow.
    np.testing.assert_array_equal(points[:n_hits], np.concatenate([s.points for s in scans]))
    np.testing.assert_array_equal(labels[:n_hits], 1)
    _free_on_beams(scans, points[labels == 0], margin=0.2)


def test_points_free_stop_short_of_hit() -> None:
    # One beam along +x to 10 m: free samples in [0, 10 - short).
    scan = Scan(np.zeros(2), np.array([[10.0, 0.0]]))
    points, labels = heldout_points([scan], rng=0, free_per_beam=5000, short=0.5)
    free = points[labels == 0]
    assert free.shape == (5000, 2)
    np.testing.assert_array_equal(free[:, 1], 0.0)
    assert free[:, 0].min() >= 0.0
    assert free[:, 0].max() < 9.5
    # Uniform on [0, 9.5): mean 4.75, standard error 9.5 / sqrt(12 * 5000) ~ 0.04.
    assert abs(free[:, 0].mean() - 4.75) < 0.2


def test_points_resolution_widens_gap() -> None:
    scan = Scan(np.zeros(2), np.array([[10.0, 0.0]]))
    points, labels = heldout_points([scan], rng=0, free_per_beam=2000, short=0.1, resolution=1.0)
    assert points[labels == 0, 0].max() < 9.0
    points, labels = heldout_points([scan], rng=0, free_per_beam=2000, short=2.0, resolution=1.0)
    assert points[labels == 0, 0].max() < 8.0


def test_points_no_return_and_degenerate_beams() -> None:
    origin = np.array([1.0, 2.0, 3.0])
    ends = origin + np.array(
        [
            [4.0, 0.0, 0.0],  # a hit at 4 m
            [0.0, 8.0, 0.0],  # exactly max_range: a no-return
            [0.0, 0.0, 20.0],  # beyond max_range: free to 8 m only
            [0.0, 0.0, 0.0],  # on the sensor: nothing
            [0.05, 0.0, 0.0],  # shorter than `short`: a hit, no free point
        ]
    )
    scan = Scan(origin, ends, max_range=8.0)
    points, labels = heldout_points([scan], rng=0, free_per_beam=200, short=0.1)
    np.testing.assert_array_equal(points[labels == 1], ends[[0, 4]])
    free = points[labels == 0]
    assert free.shape == (600, 3)
    dist = np.linalg.norm(free - origin, axis=1)
    np.testing.assert_array_less(dist[:200], 3.9)
    np.testing.assert_array_less(dist[200:], 8.0)
    # The no-return beams reach beyond where a hit's margin would have stopped them.
    assert dist[200:400].max() > 7.0
    assert dist[400:].max() > 7.0


def test_points_seeded_and_vectorised_over_scans() -> None:
    rng = np.random.default_rng(5)
    scans = [_random_scan(rng, 3, 50, max_range=9.0) for _ in range(4)]
    a = heldout_points(scans, rng=np.random.default_rng(2), free_per_beam=3)
    b = heldout_points(scans, rng=2, free_per_beam=3)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    _free_on_beams(scans, a[0][a[1] == 0], margin=0.1)


def test_points_zero_free_per_beam() -> None:
    scan = Scan(np.zeros(2), np.array([[1.0, 0.0], [0.0, 2.0]]))
    points, labels = heldout_points([scan], rng=0, free_per_beam=0)
    np.testing.assert_array_equal(labels, [1, 1])
    np.testing.assert_array_equal(points, scan.points)


def test_points_rejects_bad_input() -> None:
    scan2 = Scan(np.zeros(2), np.ones((3, 2)))
    scan3 = Scan(np.zeros(3), np.ones((3, 3)))
    with pytest.raises(OctolgpError):
        heldout_points([], rng=0)
    with pytest.raises(OctolgpError):
        heldout_points([scan2, scan3], rng=0)
    with pytest.raises(OctolgpError):
        heldout_points([scan2], rng=0, free_per_beam=-1)
    with pytest.raises(OctolgpError):
        heldout_points([scan2], rng=0, short=-0.1)


# --- scores --------------------------------------------------------------------------


def test_auc_perfect_inverted_and_ties() -> None:
    labels = np.array([0, 0, 1, 1, 0, 1], dtype=np.int8)
    assert auc(labels, labels.astype(float)) == 1.0
    assert auc(labels, 1.0 - labels) == 0.0
    assert auc(labels, np.full(6, 0.5)) == 0.5
    # One free point ranked above one of three hits: 8 of 9 pairs right.
    assert auc(labels, [0.1, 0.2, 0.9, 0.8, 0.7, 0.6]) == pytest.approx(8 / 9)


def test_auc_rejects_one_class_and_bad_shapes() -> None:
    with pytest.raises(OctolgpError):
        auc([1, 1, 1], [0.2, 0.5, 0.9])
    with pytest.raises(OctolgpError):
        auc([0, 1], [0.5])
    with pytest.raises(OctolgpError):
        auc([0, 2], [0.5, 0.6])
    with pytest.raises(OctolgpError):
        auc([0, 1], [0.5, math.nan])


def test_unknown_fraction() -> None:
    assert unknown_fraction([0.5, 0.2, 0.5, 0.9]) == 0.5
    assert unknown_fraction([0.5000001]) == 0.0
    with pytest.raises(OctolgpError):
        unknown_fraction([])


class _HalfPlaneMap:
    """Occupied for x > 0, free for x < -1, unknown between."""

    def occupancy(self, points: np.ndarray) -> np.ndarray:
        x = points[:, 0]
        return np.where(x > 0, 0.9, np.where(x < -1, 0.1, 0.5))


def test_evaluate_scores_a_map() -> None:
    points = np.array([[1.0, 0.0], [2.0, 0.0], [-2.0, 0.0], [-0.5, 0.0], [-3.0, 1.0]])
    labels = np.array([1, 1, 0, 0, 0], dtype=np.int8)
    result = evaluate(_HalfPlaneMap(), points, labels)
    assert result["auc"] == 1.0
    assert result["auc_known"] == 1.0
    assert result["unknown_fraction"] == pytest.approx(0.2)
    assert result["n_points"] == 5
    assert result["n_occupied"] == 2


def test_evaluate_auc_known_nan_without_both_classes() -> None:
    points = np.array([[1.0, 0.0], [-0.5, 0.0]])
    result = evaluate(_HalfPlaneMap(), points, np.array([1, 0]))
    assert result["auc"] == 1.0
    assert math.isnan(result["auc_known"])


def test_heldout_end_to_end_with_ogm() -> None:
    from octolgp.batch.ogm import build_ogm
    from octolgp.config import MapConfig

    # A 2D room, scanned from a path; the held-out scans' points should score well.
    rng = np.random.default_rng(0)
    angles = np.linspace(-np.pi, np.pi, 181)[:-1]
    scans = []
    for k in range(40):
        pose = np.array([-2.0 + 0.1 * k, 0.2 * np.sin(0.3 * k), 0.0])
        # Square room |x|, |y| <= 5: range to the wall along each beam.
        c, s = np.cos(angles), np.sin(angles)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (5 - pose[0]) / c, (-5 - pose[0]) / c)
            ty = np.where(s > 0, (5 - pose[1]) / s, (-5 - pose[1]) / s)
        ranges = np.minimum(np.abs(tx), np.abs(ty)) + rng.normal(0, 0.005, angles.size)
        scans.append(Scan.from_ranges(pose, ranges, angles, max_range=30.0))
    train, test = heldout_split(len(scans), fraction=0.1, run=40, seed=0)
    assert test.size == 4
    config = MapConfig(dim=2, resolution=0.1)
    grid = build_ogm([scans[i] for i in train], config)
    points, labels = heldout_points([scans[i] for i in test], rng=0, resolution=0.1)
    result = evaluate(grid, points, labels)
    assert result["auc"] > 0.95


# ---------------------------------------------------------------- the hilbert protocol
def _fan(origin: tuple[float, float], ranges: list[float], max_range: float = 8.0) -> Scan:
    ang = np.linspace(0.0, np.pi, len(ranges))
    o = np.asarray(origin)
    pts = o + np.asarray(ranges)[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    return Scan(origin=o, points=pts, max_range=max_range)


def test_hilbert_points_counts_ranges_and_labels() -> None:
    ranges = [0.6, 1.9, 2.0, 5.3, 8.0, 7.99]  # 8.0: a no-return
    scans = [_fan((0.0, 0.0), ranges), _fan((1.0, -1.0), [3.0, 0.0, 4.5])]  # 0.0: on the sensor
    points, labels = hilbert_points(scans, 0, short=0.1)
    returns = [r for r in ranges if 0 < r < 8.0] + [3.0, 4.5]
    n_free = [max(1, int(d / 2)) for d in returns]
    assert int(labels.sum()) == len(returns)
    assert int((labels == 0).sum()) == sum(n_free)  # 1, 1, 1, 2, 3 | 1, 2
    # occupied first (the endpoints), then the free points, beam by beam
    occupied = points[labels == 1]
    ends = np.concatenate([s.points for s in scans])
    length = np.concatenate([np.linalg.norm(s.points - s.origin, axis=1) for s in scans])
    keep = (length > 0) & (length < 8.0)
    np.testing.assert_array_equal(occupied, ends[keep])
    # each free point lies on its beam, in [0, d - 0.1]
    free = points[labels == 0]
    origins = np.concatenate([np.repeat(s.origin[None], len(s), axis=0) for s in scans])[keep]
    beam = np.repeat(np.arange(keep.sum()), n_free)
    along = np.linalg.norm(free - origins[beam], axis=1)
    assert (along <= length[keep][beam] - 0.1 + 1e-12).all()
    direction = (ends[keep] - origins) / length[keep][:, None]
    rel = free - origins[beam]
    cross = direction[beam, 0] * rel[:, 1] - direction[beam, 1] * rel[:, 0]
    np.testing.assert_allclose(cross, 0.0, atol=1e-12)


def test_hilbert_points_are_seeded_and_spread_uniformly() -> None:
    scan = _fan((0.0, 0.0), [6.0] * 400, max_range=10.0)  # 3 free points per beam
    a, la = hilbert_points([scan], 7)
    b, lb = hilbert_points([scan], 7)
    c, _ = hilbert_points([scan], 8)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(la, lb)
    assert not np.array_equal(a, c)
    along = np.linalg.norm(a[la == 0], axis=1) / 5.9  # uniform on [0, 1]
    assert along.size == 1200
    assert abs(along.mean() - 0.5) < 0.03
    assert abs(np.quantile(along, 0.25) - 0.25) < 0.04


def test_hilbert_points_rejects_bad_input() -> None:
    with pytest.raises(OctolgpError, match="no scans"):
        hilbert_points([], 0)
    with pytest.raises(OctolgpError, match="short"):
        hilbert_points([_fan((0.0, 0.0), [1.0])], 0, short=-1.0)


def test_eval_takes_the_hilbert_protocol() -> None:
    from octolgp import MapConfig
    from octolgp.bench.evaluation import evaluate_log

    rng = np.random.default_rng(0)
    scans = [_fan((x, 0.0), list(3.0 + rng.uniform(0, 0.1, 60))) for x in np.linspace(0, 2, 12)]
    config = MapConfig(dim=2, resolution=0.2)
    with pytest.raises(OctolgpError, match="protocol"):
        evaluate_log(scans, config, seeds=1, methods=["grid"], protocol="nope")
    report = evaluate_log(scans, config, seeds=2, run=2, methods=["grid"], protocol="hilbert")
    summary = report.summary()["grid"]
    assert summary["auc_worst"] <= summary["auc_mean"]
    assert "worst split" in report.table()


def test_novel_fraction_counts_points_without_a_training_return_nearby() -> None:
    from octolgp.bench.heldout import novel_fraction

    train = [Scan(np.zeros(2), np.array([[2.0, 0.0], [0.0, 3.0], [0.0, -9.0]]), max_range=9.0)]
    pts = np.array([[2.05, 0.0], [0.0, 3.29], [0.0, 3.31], [0.0, -9.0], [5.0, 5.0]])
    # near the first two returns; the no-return end [0, -9] is no return
    assert novel_fraction(train, pts, 0.3) == 3 / 5
    assert novel_fraction(train, pts[:2], 0.3) == 0.0
    assert novel_fraction(train, np.zeros((0, 2)), 0.3) == 0.0
    only_no_returns = [Scan(np.zeros(2), np.array([[0.0, -9.0]]), max_range=9.0)]
    assert novel_fraction(only_no_returns, pts, 0.3) == 1.0


def test_seen_free_fraction_counts_novel_points_the_training_looked_through() -> None:
    from octolgp import MapConfig
    from octolgp.bench.heldout import novel_fraction, seen_free_fraction

    train = [Scan(np.zeros(2), np.array([[2.0, 0.0], [0.0, 3.0], [0.0, -9.0]]), max_range=9.0)]
    pts = np.array(
        [
            [2.05, 0.0],  # near a return: not novel
            [1.0, 0.05],  # on the first beam's free segment: novel, looked through
            [0.05, -5.05],  # on the no-return beam: novel, looked through
            [5.0, 5.0],  # never seen
            [0.0, 3.31],  # beyond the second return: novel, never looked through
        ]
    )
    config = MapConfig(dim=2, resolution=0.1)
    assert novel_fraction(train, pts, 0.3) == 4 / 5
    assert seen_free_fraction(train, pts, 0.3, config) == 2 / 5
    assert seen_free_fraction(train, pts[[0, 3, 4]], 0.3, config) == 0.0
    assert seen_free_fraction(train, np.zeros((0, 2)), 0.3, config) == 0.0
    # a point the training hit is never counted, even where other beams crossed it
    assert seen_free_fraction(train, pts[:1], 0.3, config) == 0.0
