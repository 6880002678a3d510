"""Partitioning: size cap of iterative k-means, overlap, segment ownership, clipping."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from sklearn.exceptions import ConvergenceWarning

from octolgp.config import MapConfig, PartitionConfig
from octolgp.geometry.boxes import clip_to_box
from octolgp.partition import Cluster, partition, split_under_cap
from octolgp.training import TrainingData

RESOLUTION = 0.1
CAP = 40


@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 120),
    cap=st.integers(2, 30),
    max_weight=st.integers(1, 4),
)
def test_split_under_cap_partitions_and_respects_cap(
    seed: int, n: int, cap: int, max_weight: int
) -> None:
    """Distinct hits: every group within the cap unless it is a single hit."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 10, (n, 2))
    weight = rng.integers(1, max_weight + 1, n)
    groups = split_under_cap(points, weight, cap, seed=0)
    members = np.concatenate(groups)
    np.testing.assert_array_equal(np.sort(members), np.arange(n))  # a partition of the hits
    for g in groups:
        assert g.size >= 1
        assert weight[g].sum() <= cap or g.size == 1


def test_split_under_cap_single_group_when_under_cap() -> None:
    points = np.random.default_rng(0).uniform(0, 1, (10, 3))
    groups = split_under_cap(points, np.ones(10, dtype=np.int64), 10, seed=0)
    assert len(groups) == 1
    np.testing.assert_array_equal(groups[0], np.arange(10))


def test_split_under_cap_coincident_hits() -> None:
    """Three hits at one place with two items each, cap 3: each must go alone."""
    points = np.zeros((3, 2))
    weight = np.full(3, 2, dtype=np.int64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        groups = split_under_cap(points, weight, 3, seed=0)
    np.testing.assert_array_equal(np.sort(np.concatenate(groups)), np.arange(3))
    assert all(weight[g].sum() <= 3 or g.size == 1 for g in groups), groups
    assert not [w for w in caught if issubclass(w.category, ConvergenceWarning)]


# --------------------------------------------------------------------------- partition


def _scene(seed: int = 0) -> TrainingData:
    """Hits on the walls of a 24 × 12 m room, short free segments, and no-returns.

    Each hit's free segment starts 1.5 m inside the room, along the wall normal,
    and stops one resolution short of the hit; the no-returns are 15 m beams from a
    sensor at (6, 6).
    """
    rng = np.random.default_rng(seed)
    n = 60
    along = rng.uniform(0.5, 23.5, (2, n))
    up = rng.uniform(0.5, 11.5, (2, n // 2))
    hits = np.concatenate(
        [
            np.column_stack([along[0], np.zeros(n)]),
            np.column_stack([along[1], np.full(n, 12.0)]),
            np.column_stack([np.zeros(n // 2), up[0]]),
            np.column_stack([np.full(n // 2, 24.0), up[1]]),
        ]
    )
    inward = np.concatenate(
        [
            np.tile(v, (m, 1))
            for v, m in [([0, 1], n), ([0, -1], n), ([1, 0], n // 2), ([-1, 0], n // 2)]
        ]
    ).astype(float)
    angles = rng.uniform(0, 2 * np.pi, 30)
    nr_start = np.tile([6.0, 6.0], (30, 1))
    nr_end = nr_start + 15.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    return TrainingData(
        hits=hits,
        seg_start=np.concatenate([hits + 1.5 * inward, nr_start]),
        seg_end=np.concatenate([hits + RESOLUTION * inward, nr_end]),
        seg_hit=np.concatenate([np.arange(hits.shape[0]), np.full(30, -1)]).astype(np.int64),
    )


def _config(overlap: float = 0.2) -> MapConfig:
    return MapConfig(
        dim=2,
        resolution=RESOLUTION,
        partition=PartitionConfig(box_size=10.0, max_cluster_size=CAP, overlap=overlap),
    )


def _weight(data: TrainingData) -> np.ndarray:
    own = data.seg_hit >= 0
    return 1 + np.bincount(data.seg_hit[own], minlength=data.hits.shape[0])


def _own_groups(data: TrainingData, clusters: list[Cluster]) -> list[np.ndarray]:
    """Each cluster's own hits: coarse boxes, then iterative k-means, matched by centre."""
    pc = _config().partition
    weight = _weight(data)
    _, box_of = np.unique(np.floor(data.hits / pc.box_size), axis=0, return_inverse=True)
    groups = []
    for b in np.unique(box_of):
        members = np.flatnonzero(box_of.ravel() == b)
        for g in split_under_cap(data.hits[members], weight[members], CAP, pc.seed):
            groups.append(members[g])
    means = np.array([data.hits[g].mean(axis=0) for g in groups])
    own = []
    for c in clusters:
        match = np.flatnonzero(np.all(np.isclose(means, c.centre, rtol=0, atol=1e-12), axis=1))
        assert match.size == 1, "a cluster centre is not the mean of exactly one own group"
        own.append(groups[match[0]])
    return own


@pytest.fixture(scope="module")
def data() -> TrainingData:
    return _scene()


@pytest.fixture(scope="module")
def clusters_by_overlap(data: TrainingData) -> dict[float, list[Cluster]]:
    return {f: partition(data, _config(), overlap=f) for f in (0.0, 0.2, 0.5)}


@pytest.fixture(scope="module")
def own(data: TrainingData, clusters_by_overlap: dict[float, list[Cluster]]) -> list[np.ndarray]:
    return _own_groups(data, clusters_by_overlap[0.0])


def test_own_hits_partition_the_hits_under_the_cap(
    data: TrainingData, clusters_by_overlap: dict[float, list[Cluster]], own: list[np.ndarray]
) -> None:
    """Own groups are disjoint and cover every hit; each sits in its own cluster."""
    clusters = clusters_by_overlap[0.0]
    assert len(clusters) > 4  # the scene really is split
    np.testing.assert_array_equal(np.sort(np.concatenate(own)), np.arange(data.hits.shape[0]))
    weight = _weight(data)
    assert sum(c.n_own for c in clusters) == weight.sum()
    for c, g in zip(clusters, own, strict=True):
        assert c.n_own == weight[g].sum()
        assert c.n_own <= CAP or g.size == 1
        assert np.isin(g, c.hits).all()  # every hit is in its own cluster
        # an own group never straddles two coarse boxes
        assert np.unique(np.floor(data.hits[g] / 10.0), axis=0).shape[0] == 1


@pytest.mark.parametrize("overlap", [0.0, 0.2, 0.5])
def test_cluster_hits_are_own_plus_hits_in_region_thinned_to_cap(
    data: TrainingData,
    clusters_by_overlap: dict[float, list[Cluster]],
    own: list[np.ndarray],
    overlap: float,
) -> None:
    for c, g in zip(clusters_by_overlap[overlap], own, strict=True):
        lo, hi = data.hits[g].min(axis=0), data.hits[g].max(axis=0)
        assert np.all(c.lo <= lo)
        assert np.all(c.hi >= hi)
        inside = np.flatnonzero(((data.hits >= c.lo) & (data.hits <= c.hi)).all(axis=1))
        shared = np.setdiff1d(c.hits, g)
        assert np.isin(shared, inside).all()
        room = max(CAP - g.size, 0)
        assert shared.size == min(room, np.setdiff1d(inside, g).size)
        assert c.hits.size <= max(CAP, g.size)


def test_overlap_grows_each_region_by_its_extent(
    clusters_by_overlap: dict[float, list[Cluster]],
) -> None:
    """Region(f) = region(0) grown by f × max(extent, 2 resolution) on every side."""
    base = clusters_by_overlap[0.0]
    for f in (0.2, 0.5):
        for c0, c in zip(base, clusters_by_overlap[f], strict=True):
            np.testing.assert_allclose(c.centre, c0.centre)
            margin = f * np.maximum(c0.hi - c0.lo, 2 * RESOLUTION)
            np.testing.assert_allclose(c.lo, c0.lo - margin)
            np.testing.assert_allclose(c.hi, c0.hi + margin)


def test_regions_reach_at_most_half_a_box_beyond_own_hits(
    data: TrainingData, clusters_by_overlap: dict[float, list[Cluster]], own: list[np.ndarray]
) -> None:
    for c, g in zip(clusters_by_overlap[0.0], own, strict=True):
        assert np.all(c.lo >= data.hits[g].min(axis=0) - 5.0 - 1e-12)
        assert np.all(c.hi <= data.hits[g].max(axis=0) + 5.0 + 1e-12)


def test_overlap_makes_neighbours_share_hits(
    clusters_by_overlap: dict[float, list[Cluster]],
) -> None:
    def shared_pairs(clusters: list[Cluster]) -> int:
        return sum(
            np.intersect1d(a.hits, b.hits).size > 0 for a, b in itertools.combinations(clusters, 2)
        )

    counts = [shared_pairs(clusters_by_overlap[f]) for f in (0.0, 0.2, 0.5)]
    assert counts[0] < counts[1] <= counts[2], counts
    assert counts[1] >= len(clusters_by_overlap[0.2]) // 2


def _inside_length(
    a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, m: int = 4001
) -> np.ndarray:
    """Length of each segment inside a box, by dense sampling (error <= length / (m - 1))."""
    t = np.linspace(0.0, 1.0, m)
    samples = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    inside = ((samples >= lo) & (samples <= hi)).all(axis=2)
    return inside.sum(axis=1) / (m - 1) * np.linalg.norm(b - a, axis=1) * (inside.any(axis=1))


@pytest.mark.parametrize("overlap", [0.0, 0.5])
def test_free_pieces_are_segments_clipped_to_the_region(
    data: TrainingData, clusters_by_overlap: dict[float, list[Cluster]], overlap: float
) -> None:
    """Every piece lies in the region on one free segment (own, shared or no-return).

    Pieces shorter than half a resolution are dropped, and at most the cap are kept.
    """
    a, b = data.seg_start, data.seg_end
    unit = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    seen_no_return = False
    for c in clusters_by_overlap[overlap]:
        assert c.seg_start.shape == c.seg_end.shape
        for p in (c.seg_start, c.seg_end):
            assert np.all(p >= c.lo - 1e-9)
            assert np.all(p <= c.hi + 1e-9)
        assert np.all(np.linalg.norm(c.seg_end - c.seg_start, axis=1) > 0.5 * RESOLUTION)
        for s, e in zip(c.seg_start, c.seg_end, strict=True):
            # distance of both piece ends to each original segment (line and extent)
            ts = np.einsum("ij,ij->i", s - a, unit)
            te = np.einsum("ij,ij->i", e - a, unit)
            off_s = np.linalg.norm(s - a - ts[:, None] * unit, axis=1)
            off_e = np.linalg.norm(e - a - te[:, None] * unit, axis=1)
            length = np.linalg.norm(b - a, axis=1)
            on = (off_s < 1e-9) & (off_e < 1e-9) & (ts >= -1e-9) & (te <= length + 1e-9)
            on &= te > ts  # same direction as the beam
            assert on.any()
            seen_no_return |= bool((data.seg_hit[on] < 0).any())
        # count: every segment with more than half a resolution inside, up to the cap
        length_in = _inside_length(a, b, c.lo, c.hi)
        tol = np.linalg.norm(b - a, axis=1) / 4000 + 1e-9
        lo_count = min(CAP, int((length_in > 0.5 * RESOLUTION + tol).sum()))
        hi_count = min(CAP, int((length_in > 0.5 * RESOLUTION - tol).sum()))
        assert lo_count <= c.seg_start.shape[0] <= hi_count
    assert seen_no_return


def test_free_segments_go_with_their_hits(
    data: TrainingData, clusters_by_overlap: dict[float, list[Cluster]]
) -> None:
    """Where nothing is thinned, a hit's free segment ending in the region is a whole piece."""
    checked = 0
    for c in clusters_by_overlap[0.2]:
        if c.seg_start.shape[0] >= CAP:  # pieces thinned at random
            continue
        for h in c.hits:
            for i in np.flatnonzero(data.seg_hit == h):
                if np.all((data.seg_start[i] >= c.lo) & (data.seg_start[i] <= c.hi)):
                    whole = np.all(np.isclose(c.seg_start, data.seg_start[i]), axis=1)
                    whole &= np.all(np.isclose(c.seg_end, data.seg_end[i]), axis=1)
                    assert whole.any()
                    checked += 1
    assert checked > data.hits.shape[0] // 2


def test_partition_of_no_hits_is_empty() -> None:
    empty = TrainingData(
        hits=np.zeros((0, 2)),
        seg_start=np.zeros((1, 2)),
        seg_end=np.ones((1, 2)),
        seg_hit=np.array([-1]),
    )
    assert partition(empty, _config()) == []


# --------------------------------------------------------------------------- clipping


@pytest.mark.parametrize("d", [2, 3])
def testclip_to_box_matches_dense_sampling(d: int) -> None:
    """Liang-Barsky against 20 001 samples per segment (entry/exit within one step)."""
    rng = np.random.default_rng(d)
    n = 400
    a = rng.uniform(-3, 3, (n, d))
    b = rng.uniform(-3, 3, (n, d))
    # axis-parallel segments: zero direction components, inside and outside the slab
    b[:80, 0] = a[:80, 0]
    b[40:80, 1:] = a[40:80, 1:]
    lo = np.array([-1.0, -0.5, -2.0][:d])
    hi = np.array([1.5, 0.7, 1.0][:d])
    s, e, keep = clip_to_box(a, b, lo, hi)
    t = np.linspace(0.0, 1.0, 20_001)
    samples = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    inside = ((samples >= lo) & (samples <= hi)).all(axis=2)
    np.testing.assert_array_equal(keep, inside.any(axis=1))
    assert 50 < keep.sum() < n - 50  # both outcomes are exercised
    first = np.argmax(inside, axis=1)
    last = t.size - 1 - np.argmax(inside[:, ::-1], axis=1)
    length = np.linalg.norm(b - a, axis=1)
    step = 1.0 / (t.size - 1)
    tol = (step * length + 1e-12)[keep]
    s_ref = samples[np.arange(n), first]
    e_ref = samples[np.arange(n), last]
    assert np.all(np.linalg.norm(s[keep] - s_ref[keep], axis=1) <= tol)
    assert np.all(np.linalg.norm(e[keep] - e_ref[keep], axis=1) <= tol)
