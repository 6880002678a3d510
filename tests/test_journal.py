"""The journal: rounded scans stored as steps, read back bit for bit; maps built from them."""

from __future__ import annotations

import dataclasses
import sqlite3
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_correct import journaled, office_scan, pose
from test_online import assert_same_map

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineConfig, OnlineMap, Scan
from octolgp.engines.lattice_record import decode_lattice, encode_lattice, encode_lattice_many
from octolgp.geometry.keys import pack_keys, return_steps, step_points
from octolgp.mapping.correction import transform_scan
from octolgp.mapping.grid import LeafGrid
from octolgp.persist.journal import decode_points, encode_points
from octolgp.scan import canonical_order, scan_steps
from octolgp.sim.lidar3d import simulate_lidar_room

HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
HP2 = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=5.0)


def _scan(seed: int, n: int, max_range: float | None, dim: int = 3) -> Scan:
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-50.0, 50.0, dim)
    u = rng.normal(size=(n, dim))
    u /= np.linalg.norm(u, axis=1)[:, None]
    r = rng.uniform(0.05, 30.0, n)
    if max_range is not None:
        r[::5] = max_range  # no-returns
        r[1::7] = max_range - 1e-4  # returns that rounding could carry to max_range
    return Scan(origin=origin, points=origin + u * r[:, None], max_range=max_range)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 400),
    precision=st.sampled_from([1e-4, 0.001, 0.005, 0.01, 0.05]),
    max_range=st.sampled_from([None, 30.0]),
    dim=st.sampled_from([2, 3]),
)
def test_rounding_is_idempotent_and_the_journal_exact(
    seed: int, n: int, precision: float, max_range: float | None, dim: int
) -> None:
    scan = _scan(seed, n, max_range, dim)
    rounded = scan.rounded(precision)
    order = canonical_order(scan_steps(scan, precision))
    before = scan.points[order]  # each rounded beam beside the beam it came from
    steps = np.round((rounded.points - rounded.origin) / precision)
    assert np.array_equal(np.lexsort(steps.T), np.arange(n))  # sorted, last axis first
    assert np.abs(rounded.points - before).max() <= 2 * precision * (1 + 1e-6)
    assert np.array_equal(rounded.rounded(precision).points, rounded.points)
    length = np.linalg.norm(before - scan.origin, axis=1)
    far = np.ones(n, dtype=bool)
    if max_range is not None:
        limit = max_range * (1 - 1e-9)
        after = np.linalg.norm(rounded.points - rounded.origin, axis=1)
        assert np.array_equal(length >= limit, after >= limit)  # no beam changes kind
        far = np.abs(length - limit) > 2 * precision
    # a beam away from max_range moves by at most half a step per axis
    assert np.abs(rounded.points - before)[far].max(initial=0) <= 0.5 * precision * (1 + 1e-6)
    blob = encode_points(rounded, precision)
    back = decode_points(blob, rounded.origin, dim)
    assert back.tobytes() == rounded.points.tobytes()


def test_a_corrupt_journal_blob_is_an_error() -> None:
    scan = _scan(0, 100, 30.0).rounded(0.01)
    blob = encode_points(scan, 0.01)
    with pytest.raises(OctolgpError, match="decompress"):
        decode_points(blob[:-5], scan.origin, 3)
    with pytest.raises(OctolgpError, match="length"):
        decode_points(blob, scan.origin, 2)


def test_the_map_is_built_from_the_rounded_scans() -> None:
    config = MapConfig(dim=3, resolution=0.2)
    exact = dataclasses.replace(config, online=OnlineConfig(scan_precision=None))
    room = simulate_lidar_room(2, seed=0, n_azimuth=256, n_elevation=16, max_range=20.0)
    scans = [s.downsample(0.2) for s in room.scans()]
    a = OnlineMap(dataclasses.replace(config, hyperparameters=HP))
    b = OnlineMap(dataclasses.replace(exact, hyperparameters=HP))
    a.insert_scans(scans)
    b.insert_scans([s.rounded(0.01) for s in scans])
    probe = np.concatenate([s.points for s in scans])
    assert np.array_equal(a.occupancy(probe), b.occupancy(probe))


def test_the_file_journals_compactly_and_replays_what_the_map_used(tmp_path: Path) -> None:
    room = simulate_lidar_room(3, seed=1, n_azimuth=256, n_elevation=16, max_range=20.0)
    scans = [s.downsample(0.2) for s in room.scans()]
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP)
    path = tmp_path / "m.octolgp"
    with OnlineMap(config, path=path) as m:
        m.insert_scans(scans)
    con = sqlite3.connect(path)
    rows = con.execute("SELECT length(points), codec FROM scans ORDER BY idx").fetchall()
    con.close()
    points = sum(len(s) for s in scans)
    assert all(codec == 1 for _, codec in rows)
    assert sum(n for n, _ in rows) < 8 * points  # float64 would be 24 bytes a point
    with OnlineMap.open(path, read_only=True) as back:
        journal = list(back._file.scans())  # type: ignore[union-attr]
    for got, scan in zip(journal, scans, strict=True):
        assert got.points.tobytes() == scan.rounded(0.01).points.tobytes()
        assert got.origin.tobytes() == scan.origin.tobytes()


def test_a_bad_scan_precision_names_the_field() -> None:
    for bad in (0.0, -1.0, float("nan"), 2.0, True, "0.01"):
        with pytest.raises(OctolgpError, match=r"OnlineConfig\.scan_precision"):
            OnlineConfig(scan_precision=bad)  # type: ignore[arg-type]


def _loop_mission(n: int) -> tuple[list[Scan], dict[int, np.ndarray]]:
    """``n`` scans around an office; from scan 5 on odometry drifts, the corrections undo it."""
    truth = [
        office_scan((2.0 * np.cos(a) - 0.5, 2.0 * np.sin(a) - 1.0))
        for a in np.linspace(0.0, 6.0, n)
    ]
    scans, corrections = [], {}
    for i, s in enumerate(truth, start=1):
        drift = pose(0.02 * max(i - 4, 0), -0.015 * max(i - 4, 0), 0.005 * max(i - 4, 0))
        scans.append(journaled(transform_scan(s, drift)))
        corrections[i] = np.linalg.inv(drift)
    return scans, corrections


def _corrected(
    scans: list[Scan], corrections: dict[int, np.ndarray], which: list[int]
) -> list[Scan]:
    return [
        journaled(transform_scan(s, corrections[i])) if i in which else s
        for i, s in enumerate(scans, start=1)
    ]


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_a_journal_window_keeps_the_latest_scans_and_corrects_them_exactly(
    tmp_path: Path, engine: str
) -> None:
    """With journal_scans = 4 the journal keeps 4 to 7 scans; corrections inside it equal a
    fresh build (checkpoints after the journal's start rebuilt too), older ones are refused."""
    scans, corrections = _loop_mission(22)
    online = OnlineConfig(engine=engine, journal_scans=4)
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=HP2, online=online)
    fresh_config = dataclasses.replace(config, online=OnlineConfig(engine=engine))
    path = tmp_path / "m.octolgp"
    with OnlineMap(config, path=path) as m:
        for k, scan in enumerate(scans[:13], start=1):
            m.insert_scan(scan)
            assert 0 <= k - m.journal_start <= 7
            assert len(list(m.scans())) == k - m.journal_start
        assert m.journal_start == 8  # checkpoints at 8 and 12
        with pytest.raises(OctolgpError, match=r"journal_scans = 4"):
            m.correct_scans({8: corrections[8]})
        m.correct_scans({10: corrections[10], 11: corrections[11]})  # before checkpoint 12
        done = [10, 11]
        fresh = OnlineMap(fresh_config)
        fresh.insert_scans(_corrected(scans[:13], corrections, done))
        assert_same_map(m, fresh)
        for scan in scans[13:22]:  # mapping goes on; the window moves past the correction
            m.insert_scan(scan)
            fresh.insert_scan(scan)
        assert m.journal_start == 16
        m.correct_scans({17: corrections[17], 22: corrections[22]})
        done += [17, 22]
        fresh = OnlineMap(fresh_config)
        fresh.insert_scans(_corrected(scans[:22], corrections, done))
        assert_same_map(m, fresh)
        saved = tmp_path / "saved.octolgp"
        m.save(saved)
    for p in (path, saved):  # the file, and a copy of it, correct as the live map did
        with OnlineMap.open(p) as back:
            assert back.journal_start == 16
            assert_same_map(back, fresh)
            back.correct_scans({18: corrections[18]})
            again = OnlineMap(fresh_config)
            again.insert_scans(_corrected(scans[:22], corrections, [*done, 18]))
            assert_same_map(back, again)


def test_a_budgeted_map_keeps_a_journal_window_in_its_spill_file() -> None:
    scans, corrections = _loop_mission(14)
    online = OnlineConfig(journal_scans=5)
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=HP2, online=online)
    m = OnlineMap(dataclasses.replace(config, memory_budget_mb=0.05))
    m.insert_scans(scans)
    assert m.store.evictions > 0
    assert m.journal_start == 5
    m.correct_scans({12: corrections[12]})
    fresh = OnlineMap(dataclasses.replace(config, online=OnlineConfig()))
    fresh.insert_scans(_corrected(scans, corrections, [12]))
    assert_same_map(m, fresh)
    m.close()


def test_a_bad_journal_window_names_the_field() -> None:
    for bad in (0, -3, 2.5, True):
        with pytest.raises(OctolgpError, match=r"OnlineConfig\.journal_scans"):
            OnlineConfig(journal_scans=bad)  # type: ignore[arg-type]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), dim=st.sampled_from([2, 3]))
def test_lattice_records_round_trip_and_the_batch_encoder_writes_the_same_bytes(
    seed: int, dim: int
) -> None:
    """Leaves whose returns are their occupied voxels at cell centres (the usual kind), some
    listed (a return without an occupied count), some at any position (older files), some
    unsized: every record decodes to its evidence, and many at once encode the same."""
    config = MapConfig(dim=dim, resolution=0.2)
    grid = LeafGrid.from_config(config)
    rng = np.random.default_rng(seed)
    box = grid.side + 2 * grid.halo_voxels
    n_halo = box**dim
    records = []
    for kind in range(8):
        index = rng.integers(100, (1 << 16) // grid.side - 100, dim)
        if kind == 7:  # nothing seen yet
            records.append(
                (np.zeros((2, 0), np.uint8), np.zeros(0, np.int64), np.zeros((0, dim)), index)
            )
            continue
        counts = (rng.random((2, n_halo)) < 0.2) * rng.integers(1, 6, (2, n_halo))
        counts = counts.astype(np.uint8)
        flat = np.flatnonzero(counts[0])
        if kind == 3 and flat.size:  # a return where no occupied count is (listed)
            counts[0, flat[0]] = 0
        local = np.stack([(flat // box**a) % box for a in range(dim)], axis=1)
        keys = local + index * grid.side - grid.halo_voxels
        points = (keys - (1 << (grid.tree_depth - 1)) + rng.random(keys.shape)) * 0.2
        if kind != 5:  # kind 5: positions as an older file kept them
            points = step_points(return_steps(points, keys, 0.2, 16), keys, 0.2, 16)
        records.append((counts, pack_keys(keys), points, index))
    one = [encode_lattice(c, k, p, i, grid) for c, k, p, i in records]
    many = encode_lattice_many(
        [r[0] for r in records], [r[1] for r in records], [r[2] for r in records],
        np.stack([r[3] for r in records]), grid,
    )  # fmt: skip
    assert one == many
    for blob, (counts, keys, points, index) in zip(one, records, strict=True):
        c, k, p = decode_lattice(blob, index, grid)
        assert c.tobytes() == counts.tobytes()
        assert k.tobytes() == keys.tobytes()
        assert p.tobytes() == np.asarray(points, dtype=np.float64).tobytes()


def test_a_version_5_blob_with_kept_points_reads_back() -> None:
    """Files of version 5 kept no-return beams as float64 and stored 4-byte steps."""
    origin = np.array([1.5, -2.0, 0.25])
    steps = np.array([[3, -4, 5], [0, 0, 0], [-7, 2, 1]], dtype=np.int64)
    kept = np.array([False, True, False])
    kept_point = np.array([[31.123456789, 2.0, -0.5]])
    diffs = np.diff(steps.T, axis=1, prepend=0)
    shuffled = (
        np.ascontiguousarray(diffs.astype("<i4")).view(np.uint8).reshape(3, 3, 4).transpose(0, 2, 1)
    )
    raw = b"".join(
        [
            struct.pack("<dIIB", 0.01, 3, 1, 4),
            np.packbits(kept, bitorder="little").tobytes(),
            kept_point.astype("<f8").tobytes(),
            np.ascontiguousarray(shuffled).tobytes(),
        ]
    )
    back = decode_points(zlib.compress(raw), origin, 3)
    want = origin + steps * 0.01
    want[1] = kept_point[0]
    assert back.tobytes() == want.tobytes()


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_a_map_in_memory_keeps_the_journal_window_a_file_keeps(tmp_path: Path, engine: str) -> None:
    """Without a file the journal, its checkpoints and their leaf records live in RAM, as
    the file keeps them: corrections give the same map bit for bit, and older scans are
    refused alike."""
    from test_online import evidence_bytes, snapshot

    scans, corrections = _loop_mission(22)
    online = OnlineConfig(engine=engine, journal_scans=4)
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=HP2, online=online)
    with OnlineMap(config, path=tmp_path / "m.octolgp") as on_disk:
        in_ram = OnlineMap(config)

        def same() -> None:
            assert snapshot(in_ram) == snapshot(on_disk)
            assert in_ram.journal_start == on_disk.journal_start
            kept = in_ram._ram_journal
            assert kept is not None
            assert on_disk._file is not None
            assert kept.checkpoints == on_disk._file.checkpoints
            rows = [sorted(j.checkpoint_rows()) for j in (kept, on_disk._file)]
            assert [r[:2] for r in rows[0]] == [r[:2] for r in rows[1]]
            for (c, key, a_blob), (_, _, b_blob) in zip(*rows, strict=True):
                a_leaf = kept.checkpoint_leaves(c, [key])[key]
                b_leaf = on_disk._file.checkpoint_leaves(c, [key])[key]
                assert (a_blob is None) == (b_blob is None)
                if a_leaf is not None and b_leaf is not None:  # the evidence; stamps may differ
                    assert evidence_bytes(a_leaf) == evidence_bytes(b_leaf)
            for a, b in zip(in_ram.scans(), on_disk.scans(), strict=True):
                assert a.points.tobytes() == b.points.tobytes()

        for m in (on_disk, in_ram):
            m.insert_scans(scans[:13])
            with pytest.raises(OctolgpError, match=r"journal_scans = 4"):
                m.correct_scans({8: corrections[8]})
            m.correct_scans({10: corrections[10], 11: corrections[11]})
        same()
        for m in (on_disk, in_ram):
            for scan in scans[13:22]:  # one by one: the window moves past the correction
                m.insert_scan(scan)
            m.correct_scans({17: corrections[17], 22: corrections[22]})
        same()
        assert in_ram.journal_start == 16
        in_ram.save(tmp_path / "saved.octolgp")
    with OnlineMap.open(tmp_path / "saved.octolgp") as back:
        assert back.journal_start == 16
        back.correct_scans({18: corrections[18]})
        in_ram.correct_scans({18: corrections[18]})
        assert snapshot(back) == snapshot(in_ram)
