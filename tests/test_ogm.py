"""The log-odds occupancy grid: DDA against brute force, golden scenes, OctoMap semantics."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.batch import ogm
from octolgp.batch.ogm import build_ogm, logodds
from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import coord_to_key, key_to_coord, pack_keys, unpack_keys
from octolgp.geometry.raycast import traverse_voxels
from octolgp.scan import Scan

RES = 0.1
L_HIT = np.float32(logodds(0.7))
L_MISS = np.float32(logodds(0.4))
L_MIN = np.float32(logodds(0.1192))
L_MAX = np.float32(logodds(0.971))

Key = tuple[int, ...]


# --- brute-force references ---------------------------------------------------------


def _key(point: np.ndarray) -> Key:
    return tuple(int(k) for k in coord_to_key(point[None, :], RES)[0])


def _chords(o: np.ndarray, e: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Length of the segment o-e inside each voxel (slab method), metres."""
    low = key_to_coord(keys, RES) - 0.5 * RES
    d = e - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (low - o) / d, (low + RES - o) / d
    inside = (o >= low) & (o < low + RES)
    enter = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    leave = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    t_in = np.maximum(enter.max(axis=1), 0.0)
    t_out = np.minimum(leave.min(axis=1), 1.0)
    chords: np.ndarray = np.maximum(t_out - t_in, 0.0) * np.linalg.norm(d)
    return chords


def _box_keys(o: np.ndarray, e: np.ndarray) -> np.ndarray:
    lo = np.minimum(coord_to_key(o[None], RES)[0], coord_to_key(e[None], RES)[0])
    hi = np.maximum(coord_to_key(o[None], RES)[0], coord_to_key(e[None], RES)[0])
    ranges = [range(a, b + 1) for a, b in zip(lo, hi, strict=True)]
    return np.array(list(itertools.product(*ranges)), dtype=np.int64)


def _slab_voxels(o: np.ndarray, e: np.ndarray) -> set[Key]:
    """Voxels the segment crosses with positive length, without the end voxel."""
    keys = _box_keys(o, e)
    crossed = {tuple(int(v) for v in k) for k in keys[_chords(o, e, keys) > 1e-9]}
    return crossed - {_key(e)}


def _dda_voxels(o: np.ndarray, e: np.ndarray) -> set[Key]:
    _, keys = traverse_voxels(o[None], e[None], RES)
    return {tuple(int(v) for v in k) for k in keys}


def _reference_ogm(scans: list[Scan]) -> dict[Key, np.float32]:
    """OctoMap insertPointCloud, one beam at a time with Python sets."""
    store: dict[Key, np.float32] = {}
    for scan in scans:
        hits: set[Key] = set()
        free: set[Key] = set()
        for p in scan.points:
            ray = p - scan.origin
            length = float(np.linalg.norm(ray))
            end = p
            if scan.max_range is not None and length >= scan.max_range:
                end = scan.origin + ray * (scan.max_range / length)
            else:
                hits.add(_key(p))
            free |= _slab_voxels(scan.origin, end)
        updates = [(k, L_MISS) for k in free - hits] + [(k, L_HIT) for k in hits]
        for k, delta in updates:
            value = store.get(k, np.float32(0.0)) + delta
            store[k] = np.clip(value, L_MIN, L_MAX)
    return store


def _as_arrays(store: dict[Key, np.float32]) -> tuple[np.ndarray, np.ndarray]:
    keys = pack_keys(np.array(list(store), dtype=np.int64))
    values = np.array(list(store.values()), dtype=np.float32)
    order = np.argsort(keys)
    return keys[order], values[order]


# --- traversal ------------------------------------------------------------------------


@pytest.mark.parametrize("dim", [2, 3])
def test_dda_matches_dense_sampling_and_slab_reference(dim: int) -> None:
    rng = np.random.default_rng(dim)
    for _ in range(25):
        o = rng.uniform(-1.0, 1.0, dim)
        e = o + rng.uniform(-1.0, 1.0, dim)
        dda = _dda_voxels(o, e)
        assert dda == _slab_voxels(o, e)
        # Dense sampling of the closed segment visits the same voxels, end included,
        # except voxels clipped for less than a sampling step.
        n = 200_001
        t = np.linspace(0.0, 1.0, n)[:, None]
        sampled_packed = np.unique(pack_keys(coord_to_key(o + t * (e - o), RES)))
        sampled = {tuple(int(v) for v in k) for k in unpack_keys(sampled_packed, dim)}
        with_end = dda | {_key(e)}
        assert sampled <= with_end
        missed = np.array(sorted(with_end - sampled), dtype=np.int64).reshape(-1, dim)
        assert (_chords(o, e, missed) < 2 * np.linalg.norm(e - o) / (n - 1)).all()


def test_dda_axis_aligned_ray() -> None:
    beam, keys = traverse_voxels([[0.05, 0.05]], [[1.05, 0.05]], RES)
    np.testing.assert_array_equal(beam, np.zeros(10))
    np.testing.assert_array_equal(keys[:, 0], 32768 + np.arange(10))
    np.testing.assert_array_equal(keys[:, 1], 32768)


def test_dda_same_voxel_yields_nothing() -> None:
    beam, keys = traverse_voxels([[0.01, 0.02, 0.03]], [[0.09, 0.08, 0.07]], RES)
    assert beam.shape == (0,)
    assert keys.shape == (0, 3)


def test_dda_batch_equals_single_rays() -> None:
    rng = np.random.default_rng(7)
    o = rng.uniform(-2, 2, (40, 3))
    e = o + rng.normal(0, 1.0, (40, 3)) * rng.uniform(0, 1, (40, 1))
    beam, keys = traverse_voxels(o, e, RES)
    assert (np.diff(beam) >= 0).all()
    for i in range(40):
        np.testing.assert_array_equal(
            keys[beam == i], traverse_voxels(o[i : i + 1], e[i : i + 1], RES)[1]
        )


point_3d = st.tuples(*[st.floats(-2.0, 2.0, allow_nan=False)] * 3)


@given(st.lists(st.tuples(point_3d, point_3d), min_size=1, max_size=8), st.sampled_from([2, 3]))
def test_dda_walks_face_neighbours_from_origin_to_end(
    segments: list[tuple[tuple[float, ...], tuple[float, ...]]], dim: int
) -> None:
    # Holds even for degenerate rays (through edges, corners, on borders).
    o = np.array([s[0][:dim] for s in segments])
    e = np.array([s[1][:dim] for s in segments])
    beam, keys = traverse_voxels(o, e, RES)
    key_o, key_e = coord_to_key(o, RES), coord_to_key(e, RES)
    counts = np.bincount(beam, minlength=len(o))
    np.testing.assert_array_equal(counts, np.abs(key_e - key_o).sum(axis=1))
    for i in np.flatnonzero(counts):
        walk = np.vstack([keys[beam == i], key_e[i]])
        np.testing.assert_array_equal(walk[0], key_o[i])
        np.testing.assert_array_equal(np.abs(np.diff(walk, axis=0)).sum(axis=1), 1)


def test_dda_rejects_bad_input() -> None:
    with pytest.raises(OctolgpError, match="ends"):
        traverse_voxels([[0.0, 0.0]], [[0.0, 0.0, 0.0]], RES)
    with pytest.raises(OctolgpError, match="origins"):
        traverse_voxels([[np.nan, 0.0]], [[0.0, 0.0]], RES)
    with pytest.raises(OctolgpError, match=r"ends row 0 .*outside the addressable range"):
        traverse_voxels([[0.0, 0.0]], [[0.0, 4000.0]], RES)
    with pytest.raises(OctolgpError, match="equal shapes"):
        traverse_voxels([[0.0, 0.0]], [[0.0, 0.0], [1.0, 1.0]], RES)


# --- golden scenes --------------------------------------------------------------------


@pytest.mark.parametrize(("dim", "half", "n_hit", "n_free"), [(2, 10, 80, 361), (3, 5, 602, 729)])
def test_golden_room_of_rays(dim: int, half: int, n_hit: int, n_free: int) -> None:
    # Rays from a voxel centre to every voxel centre on the shell of a square (cube)
    # of half-width `half` voxels: the shell is hit, every voxel inside is free.
    offsets = np.array(list(itertools.product(range(-half, half + 1), repeat=dim)))
    shell = offsets[np.abs(offsets).max(axis=1) == half]
    origin = np.full(dim, 0.5 * RES)
    scan = Scan(origin=origin, points=origin + shell * RES)
    grid = build_ogm([scan], MapConfig(dim=dim, resolution=RES))
    assert grid.n_voxels == n_hit + n_free
    assert (grid.log_odds == L_HIT).sum() == n_hit
    assert (grid.log_odds == L_MISS).sum() == n_free
    inside = offsets[np.abs(offsets).max(axis=1) < half]
    np.testing.assert_array_equal(grid.log_odds_at(origin + inside * RES), L_MISS)
    np.testing.assert_array_equal(grid.log_odds_at(origin + shell * RES), L_HIT)


def test_golden_sphere_of_rays() -> None:
    # A sphere of rays of radius 1 m: hits lie on a one-voxel shell, free voxels inside.
    rng = np.random.default_rng(3)
    d = rng.normal(size=(20_000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    origin = np.full(3, 0.05)
    points = origin + d * 1.0
    grid = build_ogm([Scan(origin=origin, points=points)], MapConfig(dim=3, resolution=RES))
    radius = np.linalg.norm(grid.voxel_centres() - origin, axis=1)
    hit = grid.log_odds == L_HIT
    assert hit.sum() == len(np.unique(pack_keys(coord_to_key(points, RES))))
    assert (np.abs(radius[hit] - 1.0) <= RES * np.sqrt(3) / 2).all()
    assert (radius[~hit] < 1.0 + RES * np.sqrt(3) / 2).all()
    assert (grid.log_odds[~hit] == L_MISS).all()
    # Near the origin every voxel is seen free.
    near = np.array(list(itertools.product(range(-3, 4), repeat=3))) * RES + origin
    np.testing.assert_array_equal(grid.log_odds_at(near), L_MISS)


# --- OctoMap semantics -----------------------------------------------------------------


def _random_scans(rng: np.random.Generator, n_scans: int, dim: int) -> list[Scan]:
    scans = []
    for _ in range(n_scans):
        origin = rng.uniform(-0.5, 0.5, dim)
        points = origin + rng.normal(0, 0.6, (12, dim))
        scans.append(Scan(origin=origin, points=points, max_range=0.9))
    return scans


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("small_batches", [False, True])
def test_matches_beam_by_beam_reference(
    dim: int, small_batches: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if small_batches:  # many batches and traversal chunks, each a few scans
        monkeypatch.setattr(ogm, "_MAX_BATCH_VOXELS", 40)
        monkeypatch.setattr(ogm, "_MAX_BATCH_SCANS", 3)
    scans = _random_scans(np.random.default_rng(10 + dim), 30, dim)
    grid = build_ogm(iter(scans), MapConfig(dim=dim, resolution=RES))
    keys, values = _as_arrays(_reference_ogm(scans))
    np.testing.assert_array_equal(grid.keys, keys)
    np.testing.assert_array_equal(grid.log_odds, values)


def test_clamping_and_update_order() -> None:
    origin = np.array([0.05, 0.05])
    wall = Scan(origin=origin, points=np.array([[0.55, 0.05]]))
    through = Scan(origin=origin, points=np.array([[1.05, 0.05]]))
    config = MapConfig(dim=2, resolution=RES)
    grid = build_ogm([wall] * 20, config)
    assert grid.log_odds_at([[0.55, 0.05]])[0] == L_MAX
    assert grid.log_odds_at([[0.25, 0.05]])[0] == L_MIN
    # Clamped, then one miss: log-odds leave the upper bound by exactly one miss.
    grid = build_ogm([wall] * 20 + [through], config)
    assert grid.log_odds_at([[0.55, 0.05]])[0] == np.float32(L_MAX + L_MISS)
    assert grid.log_odds_at([[1.05, 0.05]])[0] == L_HIT


def test_one_update_per_scan_and_occupied_wins() -> None:
    origin = np.array([0.05, 0.05])
    # Beam 0 ends in voxel (0.55, 0.05); beams 1-3 pass through it.
    points = np.array([[0.55, 0.05], [1.05, 0.05], [1.05, 0.07], [0.95, 0.04]])
    grid = build_ogm([Scan(origin=origin, points=points)], MapConfig(dim=2, resolution=RES))
    assert grid.log_odds_at([[0.55, 0.05]])[0] == L_HIT
    assert grid.log_odds_at([[0.25, 0.05]])[0] == L_MISS
    assert grid.log_odds_at([[1.05, 0.05]])[0] == L_HIT
    assert grid.log_odds_at([[0.95, 0.05]])[0] == L_HIT  # also crossed by beam 1


def test_no_return_is_free_up_to_max_range() -> None:
    origin = np.array([0.05, 0.05])
    scan = Scan(origin=origin, points=np.array([[5.05, 0.05], [0.05, 1.05]]), max_range=1.0)
    grid = build_ogm([scan], MapConfig(dim=2, resolution=RES))
    # Both beams reach max_range: ten free voxels each (sharing the origin's), no hit.
    assert grid.n_voxels == 19
    assert (grid.log_odds == L_MISS).all()
    xs = np.c_[0.05 + RES * np.arange(10), np.full(10, 0.05)]
    assert grid.known_mask(xs).all()
    np.testing.assert_array_equal(grid.occupancy([[1.05, 0.05], [3.0, 0.05], [5.05, 0.05]]), 0.5)


def test_unknown_is_exactly_half() -> None:
    grid = build_ogm([], MapConfig(dim=3, resolution=RES))
    assert grid.n_voxels == 0
    q = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0]])  # the second is beyond the tree
    np.testing.assert_array_equal(grid.occupancy(q), 0.5)
    mean, var = grid.latent(q)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(var, 0.0)
    assert not grid.known_mask(q).any()


def test_latent_is_log_odds_without_variance() -> None:
    scans = _random_scans(np.random.default_rng(5), 5, 2)
    grid = build_ogm(scans, MapConfig(dim=2, resolution=RES))
    q = np.random.default_rng(6).uniform(-1.5, 1.5, (500, 2))
    mean, var = grid.latent(q)
    np.testing.assert_array_equal(mean, grid.log_odds_at(q))
    np.testing.assert_array_equal(var, np.zeros(500))
    np.testing.assert_allclose(grid.occupancy(q), 1 / (1 + np.exp(-mean)))
    assert ((grid.occupancy(q) == 0.5) == ~grid.known_mask(q)).all()


@pytest.mark.parametrize("points", [[[np.nan, 0.0]], [[0.0, 0.0, 0.0]], [0.0, 0.0], [["a", "b"]]])
def test_queries_reject_bad_points(points: Any) -> None:
    grid = build_ogm(_random_scans(np.random.default_rng(1), 2, 2), MapConfig(dim=2))
    for query in (grid.occupancy, grid.latent, grid.log_odds_at, grid.known_mask):
        with pytest.raises(OctolgpError, match="points"):
            query(points)


def test_build_rejects_bad_scans() -> None:
    scan_2d = Scan(origin=np.zeros(2), points=np.array([[1.0, 0.0]]))
    with pytest.raises(OctolgpError, match=r"scans\[0\]"):
        build_ogm([scan_2d], MapConfig(dim=3))
    with pytest.raises(OctolgpError, match=r"scans\[1\]"):
        build_ogm([scan_2d, "scan"], MapConfig(dim=2))  # type: ignore[list-item]
    with pytest.raises(OctolgpError, match="config"):
        build_ogm([scan_2d], {"dim": 2})  # type: ignore[arg-type]
    far = Scan(origin=np.zeros(2), points=np.array([[5000.0, 0.0]]))
    with pytest.raises(OctolgpError, match="outside"):
        build_ogm([far], MapConfig(dim=2))
