"""Free evidence reaches every voxel a free segment passes through.

The reference is OctoMap's ray traversal (``traverse_voxels``, ``computeRayKeys``) from
the segment's origin to its end, plus the end's own voxel. Rays in general position
must give exactly that set; rays through voxel edges and corners (ties) must give a
face-connected path of voxels that each touch the segment.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octolgp import MapConfig, Scan, observations
from octolgp.config import LatticeConfig, OnlineConfig, TrainingConfig
from octolgp.geometry.keys import KEY_BITS, pack_keys
from octolgp.geometry.raycast import traverse_voxels
from octolgp.observations import _free_codes, _observe_one, observe
from octolgp.training import config_beams, split_beams, stack_beams

RESOLUTION = {2: 0.1, 3: 0.2}
OFFSET = 1 << 15  # tree depth 16


def _rays(rng: np.random.Generator, n: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays in general position: lengths from a few millimetres to 80 m, log-uniform."""
    origins = rng.uniform(-3.0, 3.0, (n, dim))
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = np.exp(rng.uniform(np.log(0.003), np.log(80.0), n))
    length[:3] = [0.004, 0.03, 80.0]  # within a voxel, under one voxel, very long
    return origins, origins + length[:, None] * direction


def _voxel(points: np.ndarray, res: float) -> np.ndarray:
    keys: np.ndarray = np.floor(points / res).astype(np.int64) + OFFSET
    return keys


def _traversal(origins: np.ndarray, ends: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Per ray its voxels: traverse_voxels, then the end's voxel (ray index, keys)."""
    beam, keys = traverse_voxels(origins, ends, res)
    n = origins.shape[0]
    beam = np.r_[beam, np.arange(n)]
    keys = np.r_[keys, _voxel(ends, res)]
    return beam, keys


def _codes(keys: np.ndarray, scan: np.ndarray) -> np.ndarray:
    dim = keys.shape[1]
    codes: np.ndarray = pack_keys(keys) | (scan.astype(np.int64) << (KEY_BITS * dim))
    return codes


def _entry_t(
    origins: np.ndarray, ends: np.ndarray, beam: np.ndarray, keys: np.ndarray, res: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per (ray, voxel): where the segment enters and leaves the closed voxel box.

    Slab method: ``t`` 0 at the origin and 1 at the end, clipped to [0, 1].
    """
    o, d = origins[beam], (ends - origins)[beam]
    low = (keys - OFFSET) * res
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (low - o) / d, (low + res - o) / d
    flat = d == 0  # an axis the segment does not move along: no constraint from it
    t_in = np.where(flat, -np.inf, np.minimum(t1, t2)).max(axis=1)
    t_out = np.where(flat, np.inf, np.maximum(t1, t2)).min(axis=1)
    return np.maximum(t_in, 0.0), np.minimum(t_out, 1.0)


@pytest.fixture(params=["dense", "sorted"])
def dedup(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Both ways of deduplicating codes: a dense map of each scan's box, and sorting."""
    if request.param == "sorted":
        monkeypatch.setattr(observations, "DENSE_CELLS", 0)
    else:
        monkeypatch.setattr(observations, "DENSE_PER_VOXEL", 10**9)
    return str(request.param)


@pytest.mark.parametrize(("dim", "n"), [(2, 1000), (3, 500)])
def test_free_codes_are_the_traversal_and_the_end_voxel(dim: int, n: int, dedup: str) -> None:
    res = RESOLUTION[dim]
    rng = np.random.default_rng(dim)
    origins, ends = _rays(rng, n, dim)
    scan = rng.integers(0, 4, n)
    beam, keys = _traversal(origins, ends, res)
    truth = np.unique(_codes(keys, scan[beam]))
    codes, near_only = _free_codes(origins, ends, scan, res, 16)
    np.testing.assert_array_equal(codes, truth)
    assert near_only.size == 0
    # one scan per ray: each ray's voxels are distinct, one per border crossed and its origin's
    codes, _ = _free_codes(origins, ends, np.arange(n), res, 16)
    crossed = np.abs(_voxel(ends, res) - _voxel(origins, res)).sum()
    assert codes.size == crossed + n


def _whole_beams_config(dim: int, clear_scans: int) -> MapConfig:
    """The test resolution, ``clear_scans``, and every no-return beam free to its end."""
    return MapConfig(
        dim=dim,
        resolution=RESOLUTION[dim],
        online=OnlineConfig(clear_scans=clear_scans),
        training=TrainingConfig(no_return_range=math.inf),
    )


def _random_scans(
    rng: np.random.Generator, n_scans: int, dim: int, reach: float = 80.0
) -> list[Scan]:
    """Scans of 150 random beams each: returns from 1 cm to ``reach``, ten no-returns."""
    scans = []
    for _ in range(n_scans):
        origin, ends = _rays(rng, 150, dim)
        origin = origin[0]
        direction = ends - ends.mean(axis=0)
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        r = np.exp(rng.uniform(np.log(0.01), np.log(reach), 150))
        r[:10] = reach  # no-returns at max_range
        scans.append(Scan(origin=origin, points=origin + r[:, None] * direction, max_range=reach))
    return scans


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("clear_scans", [0, 4])
@pytest.mark.parametrize("n_scans", [1, 4])
def test_observe_sees_free_every_voxel_a_segment_passes_through(
    dim: int, clear_scans: int, n_scans: int
) -> None:
    """Scans of random beams (returns and no-returns up to 80 m): per voxel, the scans whose
    segments' traversal or end voxel holds it, without a return of the scan there. One
    scan takes observe's one-pass path, several its general one."""
    res = RESOLUTION[dim]
    rng = np.random.default_rng(10 + dim)
    config = _whole_beams_config(dim, clear_scans)
    scans = _random_scans(rng, n_scans, dim)
    obs = observe(scans, config)
    origins, ends, max_range = stack_beams(scans)
    beams = split_beams(origins, ends, max_range, config.free_margin)
    scan = np.repeat(np.arange(len(scans)), [len(s) for s in scans])
    seg = beams.has_seg
    beam, keys = _traversal(origins[seg], beams.free_end[seg], res)
    free = set(_codes(keys, scan[seg][beam]).tolist())
    hit = set(_codes(_voxel(ends[beams.is_hit], res), scan[beams.is_hit]).tolist())
    mask = (1 << (KEY_BITS * dim)) - 1
    expected: dict[int, int] = {}
    for code in free - hit:  # one count per scan that sees the voxel free
        expected[code & mask] = expected.get(code & mask, 0) + 1
    got = {int(k): int(f) for k, f in zip(pack_keys(obs.keys), obs.frees, strict=True) if f}
    assert got == expected


@pytest.mark.parametrize("dim", [2, 3])
def test_near_only_codes_match_a_brute_force(dim: int, dedup: str) -> None:
    """Near-only: every segment of the scan through the voxel enters it within ``near`` of
    its end, ``t_enter >= 1 - near / length``."""
    res = RESOLUTION[dim]
    rng = np.random.default_rng(20 + dim)
    n = 600
    origins, ends = _rays(rng, n, dim)
    origins[n // 2 :] = origins[0]  # half of them from one sensor: voxels shared by rays
    scan = rng.integers(0, 3, n)
    length = np.linalg.norm(ends - origins, axis=1)
    near = length * rng.uniform(0.0, 1.2, n)
    near[::7] = np.inf  # a no-return: near all along
    near[1::7] = 0.0
    beam, keys = _traversal(origins, ends, res)
    t_in, _ = _entry_t(origins, ends, beam, keys, res)
    is_near = t_in >= 1.0 - near[beam] / length[beam]
    codes = _codes(keys, scan[beam])
    far = set(codes[~is_near].tolist())
    truth = np.array(sorted(set(codes[is_near].tolist()) - far), dtype=np.int64)
    all_codes, near_only = _free_codes(origins, ends, scan, res, 16, near)
    np.testing.assert_array_equal(near_only, truth)
    np.testing.assert_array_equal(all_codes, np.unique(codes))
    assert 0 < near_only.size < all_codes.size


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("block", [1, 7, 300])
def test_the_codes_do_not_depend_on_the_block_size(
    dim: int, block: int, dedup: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    res = RESOLUTION[dim]
    rng = np.random.default_rng(30 + dim)
    origins, ends = _rays(rng, 200, dim)
    scan = rng.integers(0, 3, 200)
    near = np.where(rng.random(200) < 0.2, np.inf, rng.uniform(0, 2.0, 200))
    whole = _free_codes(origins, ends, scan, res, 16, near)
    monkeypatch.setattr(observations, "BLOCK_VOXELS", block)
    blocks = _free_codes(origins, ends, scan, res, 16, near)
    np.testing.assert_array_equal(blocks[0], whole[0])
    np.testing.assert_array_equal(blocks[1], whole[1])


def _assert_path(codes: np.ndarray, origin: np.ndarray, end: np.ndarray, res: float) -> None:
    """The voxels form one face-connected path from the origin's voxel to the end's, each
    stepping one axis towards the end, and each touches the closed segment."""
    dim = origin.size
    keys = ((codes[:, None] >> (KEY_BITS * np.arange(dim))) & ((1 << KEY_BITS) - 1)).astype(int)
    k0, k1 = _voxel(origin[None], res)[0], _voxel(end[None], res)[0]
    sign = np.sign(k1 - k0)
    progress = (keys - k0) * sign  # per axis, steps towards the end
    assert ((keys == k0) | (sign != 0)).all()
    assert ((progress >= 0) & (progress <= np.abs(k1 - k0))).all()
    rank = progress.sum(axis=1)
    order = np.argsort(rank)
    np.testing.assert_array_equal(rank[order], np.arange(np.abs(k1 - k0).sum() + 1))
    assert (np.abs(np.diff(keys[order], axis=0)).sum(axis=1) == 1).all()
    if np.any(end != origin):
        t_in, t_out = _entry_t(origin[None], end[None], np.zeros(len(keys), dtype=int), keys, res)
        assert (t_in <= t_out + 1e-9).all()


TIES = [  # (origin, end, resolution): through edges and corners, along borders
    ((0.0, 0.0), (1.0, 1.0), 0.1),
    ((0.0, 0.0), (-1.0, -1.0), 0.1),
    ((0.0, 0.0), (1.0, -1.0), 0.2),
    ((0.05, 0.05), (1.05, 1.05), 0.1),
    ((0.05, 0.0), (2.05, 0.0), 0.1),
    ((0.0, 0.05), (0.0, -2.05), 0.1),
    ((0.0, 0.0), (3.0, 1.0), 0.5),
    ((0.0, 0.0), (-3.0, 1.5), 0.25),
    ((0.3, 0.1), (0.3, 0.1), 0.1),
    ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.2),
    ((0.0, 0.0, 0.0), (-1.0, -1.0, -1.0), 0.2),
    ((0.0, 0.0, 0.0), (2.0, -1.0, 0.0), 0.1),
    ((0.25, 0.25, 0.25), (-2.75, 1.25, 3.25), 0.25),
    ((0.1, 0.0, 0.0), (0.1, 0.0, 4.0), 0.2),
]


@pytest.mark.parametrize(("origin", "end", "res"), TIES)
def test_ties_give_a_face_connected_path(
    origin: tuple[float, ...], end: tuple[float, ...], res: float
) -> None:
    """Through an edge or corner the path takes the voxels of the last axis first, as
    traverse_voxels does at an exact tie; traverse_voxels' own ties depend on how its
    accumulated ``t`` round, so there the two may pick different voxels beside the
    corner (as many of them). Where the tie is exact for both (at the origin, along
    one axis) they agree."""
    o, e = np.array(origin), np.array(end)
    codes, _ = _free_codes(o[None], e[None], np.zeros(1, dtype=np.int64), res, 16)
    _assert_path(codes, o, e, res)
    beam, keys = _traversal(o[None], e[None], res)
    reference = np.unique(_codes(keys, np.zeros(beam.size, dtype=np.int64)))
    assert codes.size == reference.size
    at_origin = np.all(np.abs(o) < 1e-12) and np.all(np.abs(np.abs(e) - np.abs(e[0])) < 1e-12)
    if at_origin or np.count_nonzero(e - o) <= 1:
        np.testing.assert_array_equal(codes, reference)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(2, 3),
    st.lists(st.integers(-40, 40), min_size=6, max_size=6),
    st.sampled_from([0.1, 0.2, 0.25]),
)
def test_segments_on_a_quarter_voxel_grid_give_face_connected_paths(
    dim: int, ends: list[int], res: float
) -> None:
    """Ends on multiples of a quarter voxel: ties everywhere."""
    o = np.array(ends[:dim], dtype=float) * res / 4
    e = np.array(ends[3 : 3 + dim], dtype=float) * res / 4
    codes, near_only = _free_codes(
        o[None], e[None], np.zeros(1, dtype=np.int64), res, 16, np.array([res])
    )
    _assert_path(codes, o, e, res)
    assert set(near_only.tolist()) <= set(codes.tolist())


@pytest.mark.parametrize("dim", [2, 3])
def test_the_compiled_walk_gives_the_numpy_codes(dim: int, dedup: str) -> None:
    """The compiled walk against the numpy crossings it replaces: equal codes and near-only
    codes, on rays in general position and on rays with ends on a quarter-voxel grid
    (ties through edges and corners everywhere)."""
    res = RESOLUTION[dim]
    rng = np.random.default_rng(40 + dim)
    origins, ends = _rays(rng, 400, dim)
    grid_o = rng.integers(-40, 40, (400, dim)) * res / 4
    grid_e = rng.integers(-40, 40, (400, dim)) * res / 4
    grid_o[:100] = 0.0  # many from one corner
    for o, e in ((origins, ends), (grid_o, grid_e)):
        n = o.shape[0]
        scan = rng.integers(0, 3, n)
        near = np.where(rng.random(n) < 0.2, np.inf, rng.uniform(0, 2.0, n))
        near[::9] = 0.0
        for given_near in (None, near):
            ref = _free_codes(o, e, scan, res, 16, given_near, compiled=False)
            out = _free_codes(o, e, scan, res, 16, given_near, compiled=True)
            np.testing.assert_array_equal(out[0], ref[0])
            np.testing.assert_array_equal(out[1], ref[1])
            assert ref[0].size > n


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("clear_scans", [0, 4])
@pytest.mark.parametrize("free_evidence", ["looks", "chord"])
def test_one_scan_in_one_pass_gives_the_general_observations(
    dim: int, clear_scans: int, free_evidence: str, dedup: str
) -> None:
    """observe's one-pass path for one scan (a map of its voxels, compiled walk and
    reading) against its general numpy path: every field equal, of the same dtype and
    shape, first returns bit for bit (NaN where none), chord sums where kept. Sorted: the
    box is refused a map, and the general path serves both."""
    if not observations.ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    res = RESOLUTION[dim]
    rng = np.random.default_rng(50 + dim)
    config = dataclasses.replace(
        _whole_beams_config(dim, clear_scans), lattice=LatticeConfig(free_evidence=free_evidence)
    )
    scans = _random_scans(rng, 2, dim) + _random_scans(rng, 2, dim, reach=8.0)
    grid = Scan(origin=np.zeros(dim), points=rng.integers(-40, 40, (200, dim)) * res / 4)
    one_pass = 0
    for scan in [*scans, grid]:  # beams through voxel edges and corners too
        origins, ends, max_range = stack_beams([scan])
        beams = config_beams(origins, ends, max_range, config)
        one_pass += _observe_one(origins, ends, beams, config) is not None
        fast = observe([scan], config)
        ref = observe([scan], config, compiled=False)
        for field in dataclasses.fields(ref):
            a, b = getattr(fast, field.name), getattr(ref, field.name)
            if isinstance(b, np.ndarray):
                assert a.dtype == b.dtype, field.name
                assert a.shape == b.shape, field.name
                np.testing.assert_array_equal(a, b, err_msg=field.name)
            else:
                assert a == b, field.name
        assert ref.n_voxels > len(scan)
        assert (ref.chord is not None) == (free_evidence == "chord")
    assert one_pass >= 3 if dedup == "dense" else one_pass == 0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 999), max_size=80), st.integers(1, 1000), st.integers(1, 7))
def test_marked_cells_are_the_nonzero_cells(cells: list[int], size: int, bit: int) -> None:
    """The word-at-a-time scan of a state map lists np.flatnonzero's cells."""
    if not observations.ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    state = observations.ray_kernel.state_map(size)
    assert state.size % 8 == 0
    assert state.size >= size
    at = np.array([c for c in cells if c < size], dtype=np.int64)
    state[at] |= bit
    got = observations.ray_kernel.marked_cells(state, max(at.size, 1))
    np.testing.assert_array_equal(got, np.flatnonzero(state))


def test_marked_cells_refuses_more_cells_than_most() -> None:
    if not observations.ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    state = observations.ray_kernel.state_map(100)
    state[[3, 40, 41, 99]] = observations.ray_kernel.FAR
    np.testing.assert_array_equal(observations.ray_kernel.marked_cells(state, 4), [3, 40, 41, 99])
    with pytest.raises(ValueError, match="more than 3"):
        observations.ray_kernel.marked_cells(state, 3)


def _read_with_numpy(
    state: np.ndarray,
    low: np.ndarray,
    extent: np.ndarray,
    hit_cell: np.ndarray,
    hit_point: np.ndarray,
    weights: np.ndarray | None,
) -> dict[str, np.ndarray]:
    """read_marks' fields by numpy, as observe's one-pass path read them before."""
    rk = observations.ray_kernel
    state = state.copy()
    state[hit_cell] |= rk.HIT
    cell = np.flatnonzero(state)
    mark = state[cell]
    stride = np.cumprod(np.r_[1, extent[:-1]])
    keys = np.empty((cell.size, low.size), dtype=np.int64)
    for a in range(low.size):
        keys[:, a] = cell // stride[a] % extent[a] + low[a]
    hit = mark >= rk.HIT
    free = ~hit
    weak = free & (mark == rk.NEAR)
    first_hit = np.full((cell.size, low.size), np.nan)
    first_cells, first = np.unique(hit_cell, return_index=True)
    first_hit[np.searchsorted(cell, first_cells)] = hit_point[first]
    shares = np.zeros(0, dtype=np.int64)
    strong_shares = shares
    if weights is not None:
        shares = np.multiply(weights[cell], free, dtype=np.int64)
        strong_shares = np.where(free & ~weak, shares, 0)
    return {
        "keys": keys,
        "hits": hit.astype(np.int64),
        "frees": free.astype(np.int64),
        "weak": weak.astype(np.int64),
        "strong": (free & ~weak).astype(np.int64),
        "shares": shares,
        "strong_shares": strong_shares,
        "first_hit": first_hit,
    }


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.integers(1, 9), min_size=1, max_size=3),
    st.floats(0.0, 1.0),
    st.integers(0, 30),
    st.booleans(),
    st.integers(0, 2**32 - 1),
)
def test_read_marks_is_the_numpy_reading(
    extent_list: list[int], density: float, n_hits: int, weighed: bool, seed: int
) -> None:
    """The compiled reading of a scan's state map against the numpy passes it replaces:
    every field equal and of the same dtype; the first of a cell's returns kept."""
    if not observations.ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    rk = observations.ray_kernel
    rng = np.random.default_rng(seed)
    extent = np.array(extent_list, dtype=np.int64)
    low = rng.integers(0, 1 << 15, extent.size)
    cells = int(np.prod(extent))
    state = rk.state_map(cells)
    walked = rng.random(cells) < density
    state[:cells][walked] = rng.choice([rk.FAR, rk.NEAR, rk.FAR | rk.NEAR], int(walked.sum()))
    hit_cell = rng.integers(0, cells, n_hits)  # repeats: the first return of a cell is kept
    hit_point = rng.normal(size=(n_hits, extent.size))
    weights = rng.integers(0, 1 << 20, state.size).astype(np.int32) if weighed else None
    want = _read_with_numpy(state, low, extent, hit_cell, hit_point, weights)
    got = rk.read_marks(state, low, extent, hit_cell, hit_point, cells, weights)
    for field in dataclasses.fields(got):
        a, b = getattr(got, field.name), want[field.name]
        assert a.dtype == b.dtype, field.name
        np.testing.assert_array_equal(a, b, err_msg=field.name)
    np.testing.assert_array_equal(state[:cells] >= rk.HIT, np.isin(np.arange(cells), hit_cell))
