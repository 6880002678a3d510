"""The field of view between beams (``LatticeConfig.sweep_angle``): swept space is known."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from octolgp import Hyperparameters, LatticeConfig, MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.engines.lattice import lattice_evidence
from octolgp.mapping.evidence import map_scans
from octolgp.mapping.grid import LeafGrid
from octolgp.sweep import beam_sectors, in_sector, swept_keys

HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
RES = 0.1


def _fan(origin: tuple[float, float], first: float, step: float, ranges: list[float]) -> Scan:
    """A 2D scan from ``origin``: beams every ``step`` degrees from ``first``, no-returns at 6 m."""
    ang = np.deg2rad(first + step * np.arange(len(ranges)))
    u = np.c_[np.cos(ang), np.sin(ang)]
    o = np.asarray(origin, dtype=float)
    return Scan(origin=o, points=o + u * np.asarray(ranges)[:, None], max_range=6.0)


def _scans() -> list[Scan]:
    """Sparse fans (beams 12° and 13° apart), with a depth step and no-returns."""
    return [
        _fan((0.03, 0.07), -10.0, 12.0, [4.2, 4.4, 4.6, 2.0, 2.1, 4.9, 5.0, 6.0, 6.0, 4.1]),
        _fan((1.51, -0.52), 95.0, 13.0, [3.8, 3.9, 4.0, 6.0, 3.5, 3.6, 3.7]),
        _fan((-1.02, 0.49), 200.0, 12.0, [3.0, 3.2, 3.4, 3.6]),
    ]


def _config(sweep: float, fill: int | None = None) -> MapConfig:
    return MapConfig(
        dim=2,
        resolution=RES,
        hyperparameters=HP,
        lattice=LatticeConfig(sweep_angle=sweep, fill_voxels=fill),
    )


def _brute_swept(scans: list[Scan], config: MapConfig, keys: np.ndarray) -> np.ndarray:
    """Whether each voxel (keys, (n, 2)) has its centre in a sector: the rule, pair by pair."""
    half = 1 << (config.tree_depth - 1)
    centres = (keys - half + 0.5) * config.resolution
    limit = math.radians(config.sweep_angle)
    out = np.zeros(keys.shape[0], dtype=bool)
    for scan in scans:  # a few small scans: the rule written out beam pair by beam pair
        off = scan.points - scan.origin
        r = np.hypot(off[:, 0], off[:, 1])
        no_return = r >= scan.max_range * (1.0 - 1e-9)
        reach = np.where(no_return, np.minimum(r, config.no_return_range), r - config.free_margin)
        ang = np.arctan2(off[:, 1], off[:, 0])
        order = np.lexsort((reach, ang))
        n = len(order)
        for i in range(n):
            a, b = order[i], order[(i + 1) % n]
            width = ang[b] - ang[a] + (2 * math.pi if i == n - 1 else 0.0)
            if not 0 < width <= limit:
                continue
            near = min(reach[a], reach[b])
            c = centres - scan.origin
            turn = np.mod(np.arctan2(c[:, 1], c[:, 0]) - ang[a], 2 * math.pi)
            out |= (turn <= width) & (np.hypot(c[:, 0], c[:, 1]) <= near)
    return out


def _known_keys(m: OnlineMap) -> set[tuple[int, int]]:
    """The voxels of the map that hold a value."""
    centres, _ = m.voxels()
    keys = np.floor(centres / m.config.resolution).astype(np.int64) + (
        1 << (m.config.tree_depth - 1)
    )
    return set(map(tuple, keys.tolist()))


def _observed(m: OnlineMap) -> np.ndarray:
    """Keys (n, 2) of the voxels some leaf saw free or occupied."""
    grid = LeafGrid.from_config(m.config)
    box = grid.side + 2 * grid.halo_voxels
    parts = []
    for _, leaf in m.leaves():
        ev = lattice_evidence(leaf)
        flat = np.flatnonzero((ev.counts[0] | ev.counts[1]) > 0)
        local = np.stack([flat % box, flat // box], axis=1)
        parts.append(local + leaf.index * grid.side - grid.halo_voxels)
    return np.unique(np.concatenate(parts), axis=0)


@pytest.mark.parametrize(("sweep", "fill"), [(15.0, 2), (15.0, 0), (14.0, 1), (0.0, 2)])
def test_known_voxels_are_the_brute_force_rule(sweep: float, fill: int) -> None:
    config = _config(sweep, fill).resolve()
    scans = map_scans(_scans(), config)  # as the map keeps them (rounded)
    m = OnlineMap(config)
    for scan in scans:
        m.insert_scan(scan)
    m.flush()
    half = 1 << (config.tree_depth - 1)
    lo, hi = -80 + half, 80 + half
    gx, gy = np.meshgrid(np.arange(lo, hi), np.arange(lo, hi), indexing="ij")
    keys = np.stack([gx.ravel(), gy.ravel()], axis=1)
    seen = np.zeros((hi - lo + 2 * fill, hi - lo + 2 * fill), dtype=bool)
    observed = _observed(m) - lo + fill
    seen[observed[:, 0], observed[:, 1]] = True
    swept = _brute_swept(scans, config, keys).reshape(hi - lo, hi - lo)
    seen[fill : fill + hi - lo, fill : fill + hi - lo] |= swept
    want = np.zeros((hi - lo, hi - lo), dtype=bool)
    for dx in range(2 * fill + 1):  # within fill voxels along every axis
        for dy in range(2 * fill + 1):
            want |= seen[dx : dx + hi - lo, dy : dy + hi - lo]
    got = _known_keys(m)
    assert set(map(tuple, keys[want.ravel()].tolist())) == got
    if sweep:  # the rule is not idle here: sparse beams leave swept gaps
        assert swept.sum() > 500
        m0 = OnlineMap(_config(0.0, fill))
        m0.insert_scans(scans)
        m0.flush()
        assert len(got) > len(_known_keys(m0)) + 300


def test_behind_the_hits_and_a_closed_room_read_unknown() -> None:
    # beams 14° apart stop on a wall at x = 4; a room from x = 5 no beam enters
    ang = np.deg2rad(np.arange(-28.0, 29.0, 14.0))
    u = np.c_[np.cos(ang), np.sin(ang)]
    origin = np.array([0.05, 0.05])
    scan = Scan(origin=origin, points=origin + u * (3.95 / u[:, :1]), max_range=20.0)
    m = OnlineMap(_config(15.0))
    m.insert_scan(scan)
    m.flush()
    m0 = OnlineMap(_config(0.0))
    m0.insert_scan(scan)
    m0.flush()
    # between the beams, 3.5 m out: unknown without the rule, free with it
    gap = 3.5 * np.c_[np.cos(np.deg2rad([7.0, -7.0, 21.0])), np.sin(np.deg2rad([7.0, -7.0, 21.0]))]
    assert np.all(m0.occupancy(gap) == 0.5)
    assert np.all(m.occupancy(gap) < 0.4)
    # behind the wall and in the room: exactly 0.5 with the rule too
    behind = np.stack(np.meshgrid(np.arange(4.35, 8.0, 0.1), np.arange(-2.0, 2.0, 0.1)), -1)
    assert np.all(m.occupancy(behind.reshape(-1, 2)) == 0.5)
    # outside the field of view (beyond the outer beams, and behind the sensor)
    aside = np.array([[2.0, 2.5], [2.0, -2.5], [-2.0, 0.0]])
    assert np.all(m.occupancy(aside) == 0.5)


def test_swept_keys_leave_out_only_voxels_known_anyway() -> None:
    config = _config(15.0, 2).resolve()
    scans = map_scans(_scans(), config)
    got = swept_keys(scans, config)
    half = 1 << (config.tree_depth - 1)
    gx, gy = np.meshgrid(np.arange(-80, 80) + half, np.arange(-80, 80) + half, indexing="ij")
    keys = np.stack([gx.ravel(), gy.ravel()], axis=1)
    every = _brute_swept(scans, config, keys)
    packed = keys[:, 0] | (keys[:, 1] << 16)
    assert np.isin(got, packed[every]).all()  # nothing that is not swept
    assert got.size
    assert got.size < every.sum()  # the near parts are left out
    # what is left out lies near the sensor: within (fill + 1/2) voxels of a beam
    origin, start, width, reach = beam_sectors(scans, config)
    left = keys[every & ~np.isin(packed, got)]
    centres = (left - half + 0.5) * RES
    inside = [
        in_sector(
            centres,
            np.broadcast_to(o, centres.shape),
            *(np.full(len(centres), v) for v in (s, w, r)),
        )
        for o, s, w, r in zip(origin, start, width, reach, strict=True)
    ]
    rho_ok = np.zeros(len(centres), dtype=bool)
    for o, w, hit in zip(origin, width, inside, strict=True):
        rho = np.hypot(*(centres - o).T)
        rho_ok |= hit & (rho * np.sin(w / 2) < 2.5 * RES)
    assert rho_ok.all()


def test_one_by_one_equals_one_step_and_the_file_keeps_the_swept_voxels(tmp_path) -> None:
    scans = _scans()
    one = OnlineMap(_config(15.0))
    for scan in scans:
        one.insert_scan(scan)
    one.flush()
    batch = OnlineMap(_config(15.0))
    batch.insert_batch(scans)
    path = tmp_path / "m.olgp"
    one.save(path)
    back = OnlineMap.open(path, read_only=True)
    leaves = dict(one.leaves())
    assert any(lattice_evidence(leaf).swept.any() for leaf in leaves.values())
    for other in (batch, back):
        got = dict(other.leaves())
        assert got.keys() == leaves.keys()
        for k, leaf in leaves.items():
            a, b = lattice_evidence(leaf), lattice_evidence(got[k])
            np.testing.assert_array_equal(a.counts, b.counts)
            np.testing.assert_array_equal(a.swept.any() and a.swept, b.swept.any() and b.swept)
        pts = np.random.default_rng(0).uniform(-5, 6, (4000, 2))
        np.testing.assert_array_equal(one.occupancy(pts), other.occupancy(pts))
    back.close()


def test_sweep_angle_is_checked() -> None:
    for bad in (-1.0, math.nan, 91.0, "2", True):
        with pytest.raises(OctolgpError, match=r"LatticeConfig\.sweep_angle"):
            LatticeConfig(sweep_angle=bad)  # type: ignore[arg-type]
    with pytest.raises(OctolgpError, match=r"LatticeConfig\.sweep_angle"):
        MapConfig(dim=3, lattice=LatticeConfig(sweep_angle=2.0)).resolve()
    assert MapConfig(dim=2).resolve().lattice.sweep_angle == 2.5
    assert MapConfig(dim=3).resolve().lattice.sweep_angle == 0.0
    off = dataclasses.replace(_config(0.0).resolve())
    assert swept_keys(_scans(), off).size == 0


def test_records_keep_the_swept_voxels_and_old_records_have_none() -> None:
    from octolgp.engines.lattice import LatticeEngine
    from octolgp.engines.lattice_record import (
        decode_lattice,
        decode_lattice_swept,
        encode_lattice,
        encode_lattice_many,
    )

    config = _config(15.0).resolve()
    m = OnlineMap(config)
    m.insert_batch(_scans())
    grid, engine = LeafGrid.from_config(config), LatticeEngine(config)
    leaves = [leaf for _, leaf in m.leaves()]
    evs = [lattice_evidence(leaf) for leaf in leaves]
    assert any(ev.swept.any() for ev in evs)
    assert any(not ev.swept.size for ev in evs)
    indices = np.stack([leaf.index for leaf in leaves])
    many = encode_lattice_many(
        [ev.counts for ev in evs],
        [ev.hit_keys for ev in evs],
        [ev.hits for ev in evs],
        indices,
        grid,
        [ev.swept for ev in evs],
    )
    for ev, index, blob in zip(evs, indices, many, strict=True):
        assert blob == encode_lattice(ev.counts, ev.hit_keys, ev.hits, index, grid, ev.swept)
        counts, keys, hits, swept = decode_lattice_swept(blob, index, grid)
        np.testing.assert_array_equal(counts, ev.counts)
        np.testing.assert_array_equal(keys, ev.hit_keys)
        np.testing.assert_array_equal(hits, ev.hits)
        np.testing.assert_array_equal(swept, ev.swept)
        plain = encode_lattice(ev.counts, ev.hit_keys, ev.hits, index, grid)  # as before
        assert decode_lattice_swept(plain, index, grid)[3].size == 0
        np.testing.assert_array_equal(decode_lattice(blob, index, grid)[0], ev.counts)
        back = engine.decode(engine.encode(ev), 2)
        np.testing.assert_array_equal(back.swept, ev.swept)
        np.testing.assert_array_equal(back.counts, ev.counts)


def test_a_file_from_before_the_sweep_reopens_as_it_was(tmp_path) -> None:
    import json
    import sqlite3

    path = tmp_path / "v7.olgp"
    with OnlineMap(_config(0.0), path=path) as m:
        m.insert_scans(_scans())
        m.flush()
        pts = np.random.default_rng(1).uniform(-5, 6, (3000, 2))
        before = m.occupancy(pts)
    con = sqlite3.connect(path)  # as version 7 wrote it: no sweep_angle in the config
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    del stored["lattice"]["sweep_angle"]
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.execute("UPDATE meta SET value = '7' WHERE key = 'version'")
    con.commit()
    con.close()
    with OnlineMap.open(path) as m:
        assert m.config.lattice.sweep_angle == 0.0
        np.testing.assert_array_equal(m.occupancy(pts), before)
        m.insert_scan(_scans()[0])  # goes on without sweeping, as it was made
        assert not any(lattice_evidence(leaf).swept.size for _, leaf in m.leaves())


def test_a_corrected_scan_sweeps_as_it_would_from_the_start() -> None:
    from octolgp.mapping.correction import transform_scan

    scans = _scans()
    T = np.eye(3)
    T[:2, 2] = [0.31, -0.17]
    m = OnlineMap(_config(15.0))
    m.insert_scans(scans)
    m.flush()
    m.correct_scans({2: T})
    m.flush()
    fresh = OnlineMap(_config(15.0))
    fresh.insert_scans([scans[0], transform_scan(scans[1], T), scans[2]])
    fresh.flush()
    got, want = dict(m.leaves()), dict(fresh.leaves())
    assert got.keys() == want.keys()
    assert any(lattice_evidence(leaf).swept.any() for leaf in want.values())
    for k, leaf in want.items():
        a, b = lattice_evidence(leaf), lattice_evidence(got[k])
        np.testing.assert_array_equal(a.counts, b.counts)
        np.testing.assert_array_equal(a.swept, b.swept)
    pts = np.random.default_rng(2).uniform(-5, 6, (4000, 2))
    np.testing.assert_array_equal(m.occupancy(pts), fresh.occupancy(pts))
