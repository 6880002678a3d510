"""Chord-weighted free evidence (``LatticeConfig.free_evidence = "chord"``).

Each free segment gives every voxel it passes through the voxel's share of the segment's
chord through the leaf holding the voxel. The compiled walk and its numpy form give the
same shares, both within rounding of a dense sampling of the segments; a run of scans'
summed shares, applied at once, equals the scans applied one by one; and a map built
scan by scan equals the map built at once.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_observations import _flicker_scans
from test_online import assert_same_map, config2d, room_scan

from octolgp import OnlineMap
from octolgp.config import LatticeConfig, MapConfig, OnlineConfig
from octolgp.engines.base import evidence_arrays
from octolgp.geometry import ray_kernel
from octolgp.geometry.keys import pack_keys
from octolgp.observations import (
    CHORD_CAP,
    VoxelObservations,
    _scan_codes,
    _walk_free,
    advance,
    advance_chord,
    merge_observations,
    observe,
)

RES = 0.1
BOX = 16
SAMPLES = 40_000
"""Dense samples per segment of the brute force: a box's chord of at least 1/100 of the
segment gets at least 400, so a share is sampled within 1/400."""


def _segments(rng: np.random.Generator, dim: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Random segments, some starting on voxel borders and some ending on them."""
    o = rng.uniform(-1.0, 1.0, (n, dim))
    e = o + rng.normal(0.0, 1.5, (n, dim))
    k = n // 8
    o[:k] = np.round(o[:k] / RES) * RES
    e[k : 2 * k] = o[k : 2 * k] + np.round(rng.normal(0, 1, (k, dim)) / RES) * RES
    return o, e


@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_and_numpy_shares_agree(dim: int) -> None:
    rng = np.random.default_rng(dim)
    o, e = _segments(rng, dim, 400)
    scan = rng.integers(0, 3, o.shape[0])
    near = rng.uniform(0.0, 0.5, o.shape[0])
    ref = _walk_free(o, e, scan, RES, 16, near, compiled=False, box=BOX)
    if not ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    got = _walk_free(o, e, scan, RES, 16, near, compiled=True, box=BOX)
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)
    plain = _walk_free(o, e, scan, RES, 16, near, compiled=True)
    np.testing.assert_array_equal(plain[0], got[0])  # shares change no voxel
    assert plain[2].size == 0
    for box in (1, 4):  # any power of two: boxes of one voxel get whole chords
        small = _walk_free(o, e, scan, RES, 16, near, compiled=True, box=box)
        numpy_form = _walk_free(o, e, scan, RES, 16, near, compiled=False, box=box)
        for a, b in zip(small, numpy_form, strict=True):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="power of two"):
        _walk_free(o, e, scan, RES, 16, near, compiled=True, box=12)


@pytest.mark.parametrize("dim", [2, 3])
def test_shares_are_the_chord_through_each_box(dim: int) -> None:
    """Against a dense sampling: a voxel's share is the fraction of the samples of its
    segment's chord through its box that fall in it, within 1/2048 (rounding) + 1/400
    (sampling); every voxel gets at least one unit; a segment's shares sum to about one
    per box it crosses."""
    rng = np.random.default_rng(10 + dim)
    o, e = _segments(rng, dim, 60)
    scan = np.arange(o.shape[0])  # one segment per scan: codes are per segment
    codes, _, shares = _walk_free(o, e, scan, RES, 16, compiled=False, box=BOX)
    assert shares.min() >= 1
    sampled: dict[int, float] = {}
    t = (np.arange(SAMPLES) + 0.5) / SAMPLES
    for j in range(o.shape[0]):
        points = o[j] + t[:, None] * (e[j] - o[j])
        keys = np.floor(points / RES).astype(np.int64) + (1 << 15)
        box = pack_keys(keys // BOX)
        code = _scan_codes(pack_keys(keys), np.full(SAMPLES, j), dim)
        for b in np.unique(box):
            inside = box == b
            u, n = np.unique(code[inside], return_counts=True)
            for c, k in zip(u.tolist(), n.tolist(), strict=True):
                sampled[c] = sampled.get(c, 0.0) + k / inside.sum()
    ref = np.array([sampled.get(c, 0.0) for c in codes.tolist()])
    seen = ref > 0  # voxels only touched at an edge or corner get no sample
    assert seen.mean() > 0.97
    err = np.abs(shares[seen] / ray_kernel.CHORD_UNITS - ref[seen])
    assert err.max() <= 1 / 2048 + 1 / 400


def _chord_rule(
    state: dict[int, tuple[int, int, int]], obs: VoxelObservations, config: MapConfig
) -> None:
    """One scan's observations applied to ``state`` (packed key → hits, frees, summed
    shares) as the rule states it: a free look adds its share while the free count
    counts it (below ``clear_scans``, or ``evidence_cap`` in a static world; with a
    return held, only looks counting towards forgetting), and a return restarts the sum."""
    k, cap = config.clear_scans, config.lattice.evidence_cap
    keys = pack_keys(obs.keys).tolist()
    h0, f0, _ = (np.array([state.get(x, (0, 0, 0))[i] for x in keys], np.int64) for i in range(3))
    counts = advance(h0, f0, obs, np.arange(len(keys)), cap)
    assert obs.chord is not None
    share = obs.chord[:, 0]
    for j, key in enumerate(keys):  # one iteration per voxel: the rule as stated
        h, f, w = state.get(key, (0, 0, 0))
        if obs.hits[j] and k:
            w = 0
        elif obs.frees[j]:
            strong = obs.frees[j] > obs.weak_frees[j]
            if f < (k or cap) and (not k or h == 0 or strong):
                w = min(w + int(share[j]), CHORD_CAP)
        state[key] = (int(counts.hits[j]), int(counts.frees[j]), w)


@pytest.mark.parametrize("clear", [0, 2, 5])
@pytest.mark.parametrize("cap", [1, 3])
@pytest.mark.parametrize("dim", [2, 3])
def test_summed_shares_at_once_are_the_scans_one_by_one(dim: int, cap: int, clear: int) -> None:
    rng = np.random.default_rng(10 * clear + dim + 100 * cap)
    scans = _flicker_scans(rng, dim, 14)
    config = MapConfig(
        dim=dim,
        resolution=RES,
        online=OnlineConfig(clear_scans=clear),
        lattice=LatticeConfig(free_evidence="chord", evidence_cap=cap),
    )
    state: dict[int, tuple[int, int, int]] = {}
    for scan in scans:  # the rule, scan after scan
        _chord_rule(state, observe([scan], config), config)
    want = {key: w for key, (_, _, w) in state.items()}
    whole = observe(scans, config)
    merged = merge_observations([observe(scans[:5], config), observe(scans[5:], config)], dim)
    numpy_form = observe(scans, config, compiled=False)
    for obs in (whole, merged, numpy_form):
        assert obs.chord is not None
        assert obs.strong_chord is not None
        assert obs.tail_chord is not None
        assert obs.chord.shape == (obs.n_voxels, clear or cap)
        np.testing.assert_array_equal(obs.chord, whole.chord)
        np.testing.assert_array_equal(obs.strong_chord, whole.strong_chord)
        np.testing.assert_array_equal(obs.tail_chord, whole.tail_chord)
        zero = np.zeros(obs.n_voxels, np.int64)
        got = advance_chord(zero, zero, zero, obs, np.arange(obs.n_voxels))
        assert dict(zip(pack_keys(obs.keys).tolist(), got.tolist(), strict=True)) == want
        counts = advance(zero, zero, obs, np.arange(obs.n_voxels), cap)
        assert np.all((got == 0) | (counts.hits > 0) | (counts.frees > 0))  # a record keeps it
    # two runs one after the other: the second applied to the first's state
    first = observe(scans[:6], config)
    zero = np.zeros(first.n_voxels, np.int64)
    counts = advance(zero, zero, first, np.arange(first.n_voxels), cap)
    w = advance_chord(zero, zero, zero, first, np.arange(first.n_voxels))
    second = observe(scans[6:], config)
    at = np.searchsorted(pack_keys(second.keys), pack_keys(first.keys))
    inside = at < second.n_voxels
    inside[inside] = pack_keys(second.keys)[at[inside]] == pack_keys(first.keys)[inside]
    got = w.copy()
    got[inside] = advance_chord(
        w[inside], counts.hits[inside], counts.frees[inside], second, at[inside]
    )
    first_keys = pack_keys(first.keys).tolist()
    assert dict(zip(first_keys, got.tolist(), strict=True)) == {x: want[x] for x in first_keys}
    looks = LatticeConfig(free_evidence="looks")
    assert observe(scans, dataclasses.replace(config, lattice=looks)).chord is None


def test_a_static_revisit_changes_no_sum() -> None:
    """Once a voxel's free count stops counting, the same scan again changes nothing: a
    map seeing the same scan over and over settles (no leaf refits) as with looks."""
    from octolgp import Hyperparameters
    from octolgp.sim.lidar3d import simulate_lidar_room

    room = simulate_lidar_room(2, seed=3, n_azimuth=128, n_elevation=8, max_range=8.0)
    scan = room.scans()[0].downsample(0.2)
    hp = Hyperparameters(
        length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0, beta=0.0
    )
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp).resolve()
    assert config.free_evidence == "chord"  # the 3D default
    m = OnlineMap(config)
    refits = [m.insert_scan(scan).refit_leaves for _ in range(config.clear_scans + 2)]
    assert refits[0] > 0
    assert refits[-2:] == [0, 0]


def evidence_bytes_of(evidence: object) -> list[bytes]:
    """Every array of a leaf's evidence, as bytes."""
    return [a.tobytes() for a in evidence_arrays(evidence)]  # type: ignore[arg-type]


def _chord2d(**online: object) -> MapConfig:
    return dataclasses.replace(config2d(**online), lattice=LatticeConfig(free_evidence="chord"))


def test_one_by_one_equals_all_at_once_with_chord_weights() -> None:
    scans = [room_scan((x, y)) for x, y in [(-2, -2), (0, 0), (2, 1), (-1, 2)]]
    a = OnlineMap(_chord2d())
    for s in scans:
        a.insert_scan(s)
    b = OnlineMap(_chord2d())
    b.insert_batch(scans)
    assert_same_map(a, b)
    leaf = next(iter(dict(a.leaves()).values()))
    assert leaf.evidence.chord.size == leaf.evidence.counts.shape[1]  # type: ignore[attr-defined]
    looks = OnlineMap(config2d())
    looks.insert_batch(scans)
    assert all(leaf.evidence.chord.size == 0 for _, leaf in looks.leaves())  # type: ignore[attr-defined]


def test_chord_shares_round_trip_through_records_and_the_map_file(tmp_path: Path) -> None:
    from octolgp.engines import engine_for
    from octolgp.mapping.grid import LeafGrid
    from octolgp.persist.mapfile import decode_leaf, encode_leaf

    scans = [room_scan((x, y)) for x, y in [(-2, -2), (0, 0), (2, 1), (-1, 2)]]
    config = _chord2d()
    path = tmp_path / "chord.octolgp"
    with OnlineMap(config, path=path) as m:
        m.insert_batch(scans[:3])
        codec, grid = engine_for(m.config), LeafGrid.from_config(m.config)
        leaves = list(m.leaves())
        for _key, leaf in leaves:
            ev = leaf.evidence
            assert ev.chord.any()  # type: ignore[attr-defined]
            for back in (
                codec.from_record(codec.record(ev, leaf.index), leaf.index),
                codec.decode(codec.encode(ev), 2),
                decode_leaf(encode_leaf(leaf, codec), codec, grid).evidence,
            ):
                assert evidence_bytes_of(back) == evidence_bytes_of(ev)
        many = codec.records(
            [leaf.evidence for _, leaf in leaves], np.stack([lf.index for _, lf in leaves])
        )
        assert many == [codec.record(lf.evidence, lf.index) for _, lf in leaves]
    with OnlineMap.open(path) as back:
        assert back.config == m.config
        back.insert_scan(scans[3])
        whole = OnlineMap(config)
        whole.insert_batch(scans)
        assert_same_map(back, whole)


@pytest.mark.parametrize("dim", [2, 3])
def test_records_of_many_leaves_equal_each_leafs(dim: int) -> None:
    """The batch encoder gives each leaf's record, for leaves keeping chord sums, leaves
    keeping none, unsized leaves and leaves with swept voxels mixed; a sum at a voxel
    without a count is refused, as one leaf's encoder refuses it."""
    from octolgp.engines import engine_for
    from octolgp.engines.lattice import LatticeEvidence
    from octolgp.engines.lattice_record import encode_lattice_many
    from octolgp.mapping.grid import LeafGrid

    if dim == 2:
        config = _chord2d()
        scans = [room_scan((x, y)) for x, y in [(-2, -2), (0, 0), (2, 1)]]
    else:
        from octolgp.sim.lidar3d import simulate_lidar_room

        room = simulate_lidar_room(2, seed=3, n_azimuth=128, n_elevation=8, max_range=8.0)
        scans = [s.downsample(0.2) for s in room.scans()]
        config = MapConfig(dim=3, resolution=0.2).resolve()
    m = OnlineMap(config)
    m.insert_batch(scans)
    codec, grid = engine_for(m.config), LeafGrid.from_config(m.config)
    leaves = [leaf for _, leaf in m.leaves()]
    evs = [leaf.evidence for leaf in leaves]
    assert all(ev.chord.size for ev in evs)  # type: ignore[attr-defined]
    evs[1] = dataclasses.replace(evs[1], chord=np.zeros(0, np.uint16))  # type: ignore[type-var]
    evs[2] = LatticeEvidence.empty(dim)
    n_halo = evs[3].counts.shape[1]  # type: ignore[attr-defined]
    swept = np.random.default_rng(dim).random(n_halo) < 0.2
    evs[3] = dataclasses.replace(evs[3], swept=swept)  # type: ignore[type-var]
    indices = np.stack([leaf.index for leaf in leaves])
    many = codec.records(evs, indices)
    assert many == [codec.record(ev, i) for ev, i in zip(evs, indices, strict=True)]
    ev = evs[0]
    unseen = np.flatnonzero((ev.counts[0] | ev.counts[1]) == 0)  # type: ignore[attr-defined]
    bad = ev.chord.copy()  # type: ignore[attr-defined]
    bad[unseen[0]] = 1
    with pytest.raises(ValueError, match="zero where none is seen"):
        encode_lattice_many(
            [ev.counts],  # type: ignore[attr-defined]
            [ev.hit_keys],  # type: ignore[attr-defined]
            [ev.hits],  # type: ignore[attr-defined]
            indices[:1],
            grid,
            None,
            [bad],
        )


def test_learning_weighs_free_voxels_by_their_looks() -> None:
    """The voxel observations hyperparameters are learnt on are the same with chord
    weights as with looks: each free voxel weighs ``free_weight`` times its counted looks,
    whichever weighting the leaves fit with."""
    from octolgp.gp.learning import voxel_observations

    scans = [room_scan((x, y)) for x, y in [(-2, -2), (0, 0), (2, 1)]]
    config = _chord2d(scan_precision=None).resolve()  # the scans as given
    looks = dataclasses.replace(
        config, lattice=dataclasses.replace(config.lattice, free_evidence="looks")
    )
    got = voxel_observations(scans, config)
    want = voxel_observations(scans, looks)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    _, y, weights = got
    # every free voxel weighs a whole number of looks, at most clear_scans
    looks_seen = weights[y < 0] / config.lattice.free_weight
    np.testing.assert_allclose(looks_seen, np.round(looks_seen), atol=1e-9)
    assert np.all((looks_seen >= 1) & (looks_seen <= max(1, config.clear_scans)))
    assert np.any(looks_seen > 1)


def test_one_by_one_equals_all_at_once_in_3d() -> None:
    """3D leaves share a voxel among up to eight halo boxes: every copy gets the sums."""
    from octolgp import Hyperparameters
    from octolgp.sim.lidar3d import simulate_lidar_room

    room = simulate_lidar_room(
        4, seed=0, n_azimuth=128, n_elevation=8, max_range=30.0, range_noise=0.0, n_heldout=1
    )
    scans = [s.downsample(0.2) for s in room.scans()]
    hp = Hyperparameters(
        length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0, beta=0.0
    )
    config = MapConfig(
        dim=3, resolution=0.2, hyperparameters=hp, lattice=LatticeConfig(free_evidence="chord")
    )
    a = OnlineMap(config)
    for s in scans:
        a.insert_scan(s)
    b = OnlineMap(config)
    b.insert_batch(scans)
    for m in (a, b):
        m.occupancy(np.zeros((1, 3)))  # fits the deferred leaves
    assert_same_map(a, b)


def test_stored_rows_read_every_kind_of_leaf() -> None:
    """The gather's rows of counts and sums: from a leaf holding both in one buffer (as
    the gather leaves them), in two arrays (as a map file gives them), without sums,
    not yet sized, and new; each leaf's own arrays give back its row."""
    from octolgp.engines.lattice import LatticeEvidence, _own_rows, _stored_rows
    from octolgp.mapping.store import Leaf

    rng = np.random.default_rng(5)
    n_halo = 6
    counts = rng.integers(0, 9, (4, 2, n_halo)).astype(np.uint8)
    sums = rng.integers(0, 65535, (4, n_halo)).astype(np.uint16)
    row = np.concatenate([counts[0].reshape(-1), sums[0].view(np.uint8)])
    one_buffer = _own_rows(row, n_halo)
    assert one_buffer[1] is not None
    none = np.zeros(0, np.uint16)
    hits = np.zeros(0, np.int64), np.zeros((0, 2))
    evidence = [
        LatticeEvidence(one_buffer[0], *hits, chord=one_buffer[1]),
        LatticeEvidence(counts[1].copy(), *hits, chord=sums[1].copy()),
        LatticeEvidence(counts[2].copy(), *hits, chord=none),
        LatticeEvidence(np.zeros((2, 0), np.uint8), *hits, chord=sums[3].copy()),
    ]
    leaves = [Leaf(np.zeros(2, np.int64), ev) for ev in evidence] + [None]
    rows = _stored_rows(leaves, n_halo, chord=True)
    want_counts = np.concatenate([counts[:3], np.zeros((2, 2, n_halo), np.uint8)])
    zero = np.zeros((1, n_halo), np.uint16)
    want_sums = np.concatenate([sums[:2], zero, sums[3:], zero])
    np.testing.assert_array_equal(rows[:, : 2 * n_halo].reshape(5, 2, n_halo), want_counts)
    np.testing.assert_array_equal(rows[:, 2 * n_halo :].copy().view(np.uint16), want_sums)
    for j in range(5):
        own_counts, own_sums = _own_rows(rows[j], n_halo)
        np.testing.assert_array_equal(own_counts, want_counts[j])
        assert own_sums is not None
        np.testing.assert_array_equal(own_sums, want_sums[j])
    looks = _stored_rows(leaves, n_halo, chord=False).reshape(5, 2, n_halo)
    np.testing.assert_array_equal(looks, want_counts)
    own_counts, own_sums = _own_rows(looks[0], n_halo)
    assert own_sums is None
    assert own_counts.base is None  # the leaf's own array


@pytest.mark.parametrize("clear", [0, 3])
@pytest.mark.parametrize("dim", [2, 3])
def test_one_scans_sums_are_the_general_sums(
    dim: int, clear: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The general path's sums of one scan, taken directly, against the sums of any run
    of scans (_chord_sums) on the same looks: in one scan a (scan, voxel) code is the
    voxel's packed key."""
    from octolgp import observations

    rng = np.random.default_rng(31 + dim + clear)
    config = MapConfig(
        dim=dim,
        resolution=RES,
        online=OnlineConfig(clear_scans=clear),
        lattice=LatticeConfig(free_evidence="chord"),
    )
    real = observations._one_scan_sums
    checked = []

    def both(obs: VoxelObservations, free_vox: np.ndarray, *rest: object) -> object:
        got = real(obs, free_vox, *rest)  # type: ignore[arg-type]
        hit_codes = pack_keys(obs.keys[obs.hits > 0])
        want = observations._chord_sums(obs, hit_codes, free_vox, *rest)  # type: ignore[arg-type]
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
        checked.append(bool(got[0].any()))
        return got

    monkeypatch.setattr(observations, "_one_scan_sums", both)
    for scan in _flicker_scans(rng, dim, 4):
        observe([scan], config, compiled=False)
    assert checked
    assert all(checked)
