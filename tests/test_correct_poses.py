"""Absolute poses: ``OnlineMap.correct_poses`` and ``octolgp correct --absolute``.

A pose graph's new pose ``T_new`` of a scan inserted from ``T_old`` is the correction
``T_new · T_old⁻¹``: the map it gives is exactly that of :meth:`OnlineMap.correct_scans`
with it, and a fresh build from the moved scans.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from test_correct import journaled, office_scan, pose
from test_online import HP, assert_same_map, snapshot

from octolgp import MapConfig, OctolgpError, OnlineConfig, OnlineMap, Scan
from octolgp.io.corrections import read_poses
from octolgp.mapping.correction import pose_corrections, transform_scan
from octolgp.scan import nearest_rotation, planar_rotation
from octolgp.sim.lidar3d import simulate_lidar_room


def posed_scan(x: float, y: float, yaw: float) -> Scan:
    """An office scan taken from the pose ``(x, y, yaw)``: it keeps its sensor rotation."""
    s = office_scan((x, y))
    return Scan(s.origin, s.points, s.max_range, rotation=planar_rotation(yaw, 2))


def posed_mission() -> tuple[list[Scan], dict[int, np.ndarray]]:
    """12 scans as odometry placed them (drifting from scan 6 on), and the true poses."""
    scans, truth = [], {}
    for i, a in enumerate(np.linspace(0, 5, 12), start=1):
        x, y, yaw = 2.0 * np.cos(a) - 0.5, 2.0 * np.sin(a) - 1.0, a + 0.3
        true = posed_scan(x, y, yaw)
        drift = pose(0.04 * max(i - 5, 0), -0.03 * max(i - 5, 0), 0.01 * max(i - 5, 0))
        scans.append(journaled(transform_scan(true, drift)))
        if i >= 6:
            truth[i] = pose(x, y, yaw)
    return scans, truth


def config(dim: int = 2, engine: str = "lattice", **online: object) -> MapConfig:
    return MapConfig(
        dim=dim,
        resolution=0.1 if dim == 2 else 0.2,
        hyperparameters=HP,
        online=OnlineConfig(engine=engine, **online),  # type: ignore[arg-type]
    )


def relative(m: OnlineMap, poses: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``T_new · T_old⁻¹`` from the journal's poses, by matrix inversion."""
    old = dict(enumerate(m.scans(), start=m.journal_start + 1))
    out = {}
    for i, T in poses.items():
        T_old = old[i].pose
        assert T_old is not None
        out[i] = T @ np.linalg.inv(T_old)
    return out


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_absolute_poses_give_the_map_of_their_corrections_and_of_a_fresh_build(
    tmp_path: Path, engine: str
) -> None:
    scans, truth = posed_mission()
    with OnlineMap(config(engine=engine), path=tmp_path / "m.octolgp") as m:
        m.insert_scans(scans)
        old_poses = {i: s.pose for i, s in enumerate(m.scans(), start=1)}
        corrections = relative(m, truth)
        m.correct_poses(truth)
        for i, s in enumerate(m.scans(), start=1):  # the journal holds the new poses
            assert s.pose is not None
            want = truth.get(i, old_poses[i])
            np.testing.assert_allclose(s.pose, want, rtol=0, atol=1e-12)
        journal = dict(enumerate(scans, start=1))
        exact = pose_corrections({i: journal[i] for i in truth}, truth)
        for i, T in exact.items():  # the library's T_new · T_old⁻¹, to rounding
            np.testing.assert_allclose(T, corrections[i], rtol=0, atol=1e-12)
        by_relative = OnlineMap(config(engine=engine))
        by_relative.insert_scans(scans)
        by_relative.correct_scans(exact)
        assert snapshot(m) == snapshot(by_relative)
        if engine == "lattice":  # counts on the rounded beams: the same from either matrix
            by_inverse = OnlineMap(config(engine=engine))
            by_inverse.insert_scans(scans)
            by_inverse.correct_scans(corrections)
            assert snapshot(m) == snapshot(by_inverse)
        fresh = OnlineMap(config(engine=engine))
        fresh.insert_scans(
            [
                journaled(transform_scan(s, exact[i])) if i in exact else s
                for i, s in enumerate(scans, start=1)
            ]
        )
        assert_same_map(m, fresh)
    with OnlineMap.open(tmp_path / "m.octolgp") as back:  # the file keeps the new poses
        for i, s in enumerate(back.scans(), start=1):
            if i in truth:
                assert s.pose is not None
                np.testing.assert_allclose(s.pose, truth[i], rtol=0, atol=1e-12)
        assert snapshot(back) == snapshot(by_relative)


def lidar_scans(n: int = 4) -> list[Scan]:
    room = simulate_lidar_room(n, n_azimuth=96, n_elevation=6, n_heldout=0, max_range=20.0)
    return [journaled(s) for s in room.scans()]


def test_absolute_poses_in_3d_and_in_memory(tmp_path: Path) -> None:
    """A 3D lidar's scans moved to new poses (TUM and KITTI lines), in a file and in RAM."""
    scans = lidar_scans()
    half = np.sqrt(0.5)
    new_2 = scans[1].pose
    assert new_2 is not None
    new_2 = new_2.copy()
    new_2[:3, 3] += [0.3, -0.2, 0.05]
    turn = np.eye(4)
    turn[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90° about z: quaternion (0 0 √½ √½)
    new_4 = turn.copy()
    new_4[:3, 3] = scans[3].origin + np.array([0.1, 0.0, 0.0])
    lines = [
        "# scan x y z qx qy qz qw, then a KITTI 3x4 row",
        "4 " + " ".join(repr(float(v)) for v in [*new_4[:3, 3], 0.0, 0.0, half, half]),
        "2 " + " ".join(repr(float(v)) for v in new_2[:3].ravel()),
    ]
    text = tmp_path / "optimised.txt"
    text.write_text("\n".join(lines) + "\n")
    poses = read_poses(text, 3)
    np.testing.assert_allclose(poses[4], new_4, rtol=0, atol=1e-15)
    np.testing.assert_allclose(poses[2], new_2, rtol=0, atol=1e-12)
    from octolgp.cli.main import main

    path = tmp_path / "m.octolgp"
    with OnlineMap(config(3), path=path) as m:
        m.insert_scans(scans)
        corrections = pose_corrections(dict(enumerate(m.scans(), start=1)), poses)
        for i, T in relative(m, poses).items():
            np.testing.assert_allclose(corrections[i], T, rtol=0, atol=1e-12)
    assert main(["correct", str(path), "--absolute", str(text)]) == 0
    in_ram = OnlineMap(config(3))
    in_ram.insert_scans(scans)
    in_ram.correct_poses(poses)
    by_relative = OnlineMap(config(3))
    by_relative.insert_scans(scans)
    by_relative.correct_scans(corrections)
    with OnlineMap.open(path) as back:
        assert snapshot(back) == snapshot(in_ram) == snapshot(by_relative)
        for s, r in zip(back.scans(), in_ram.scans(), strict=True):
            assert s.points.tobytes() == r.points.tobytes()
            assert s.rotation is not None
            assert r.rotation is not None
            assert s.rotation.tobytes() == r.rotation.tobytes()
    fresh = OnlineMap(config(3))
    fresh.insert_scans(
        [
            journaled(transform_scan(s, corrections[i])) if i in corrections else s
            for i, s in enumerate(scans, start=1)
        ]
    )
    assert_same_map(in_ram, fresh)


def test_octolgp_correct_absolute_2d_file(tmp_path: Path) -> None:
    from octolgp.cli.main import main

    scans, truth = posed_mission()
    path = tmp_path / "m.octolgp"
    with OnlineMap(config(), path=path) as m:
        m.insert_scans(scans)
    lines = []
    for i, T in truth.items():  # 'scan x y yaw', and 2x3 rows
        if i % 2:
            yaw = float(np.arctan2(T[1, 0], T[0, 0]))
            lines.append(f"{i} {float(T[0, 2])!r} {float(T[1, 2])!r} {yaw!r}")
        else:
            lines.append(f"{i}, " + ", ".join(repr(float(v)) for v in T[:2].ravel()))
    text = tmp_path / "poses.txt"
    text.write_text("\n".join(lines) + "\n")
    assert main(["correct", str(path), "--absolute", str(text)]) == 0
    in_ram = OnlineMap(config())
    in_ram.insert_scans(scans)
    in_ram.correct_poses(read_poses(text, 2))
    with OnlineMap.open(path) as back:
        assert snapshot(back) == snapshot(in_ram)


TUM = "1 0 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    ("dim", "text", "message"),
    [
        (2, "6 0.1 0.0\n", "poses.txt:1: scan 6: expected 3 values (a pose), 6 or 9"),
        (2, "# ok\n6 0.1 nan 0.0\n", "poses.txt:2: scan 6 has a NaN or inf value"),
        (2, "6 2 0 0 0 2 0\n", "poses.txt:1: scan 6 is not rigid"),  # a scale
        (2, "6 1 0 0 0 -1 0\n", "poses.txt:1: scan 6 is not rigid"),  # a reflection
        (2, "6 1 0 0 0 1 0 0.5 0 1\n", "poses.txt:1: scan 6 must end with the row"),
        (2, "99 0 0 0\n", "poses.txt:1: scan 99 is not in the map (scans 1..12)"),
        (2, "6 0 0 0\n7 0 0 0\n6 0 0 0\n", "poses.txt:3: scan 6 has two poses"),
        (2, "x 0 0 0\n", "poses.txt:1: scan number 'x' is not a positive integer"),
        (2, "3 0 0 0\n", "poses.txt:1: scan 3 is older than the map's journal"),
        (3, "2 0 0 0 0 0 0 2\n", "poses.txt:1: scan 2: the quaternion (qx qy qz qw) has norm 2"),
        (3, "2 0 0 0 0 0 0 0\n", "poses.txt:1: scan 2: the quaternion (qx qy qz qw) has norm 0"),
        (3, TUM + "2 1 0 0 0 0 1 0 0 0 0 1.1 0\n", "poses.txt:2: scan 2 is not rigid"),
        (3, "1 0 0 0 0 0 1\n", "poses.txt:1: scan 1: expected 7 values (a pose), 12 or 16"),
    ],
)
def test_octolgp_correct_absolute_refuses_a_bad_file_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], dim: int, text: str, message: str
) -> None:
    from octolgp.cli.main import main

    path = tmp_path / "m.octolgp"
    if dim == 2:  # a journal of scans 5 to 12
        with OnlineMap(config(journal_scans=5), path=path) as m:
            m.insert_scans(posed_mission()[0])
            assert m.journal_start == 5
    else:
        with OnlineMap(config(3), path=path) as m:
            m.insert_scans(lidar_scans(2))
    before = path.read_bytes()
    poses = tmp_path / "poses.txt"
    poses.write_text(text)
    assert main(["correct", str(path), "--absolute", str(poses)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.startswith("octolgp: error:")
    assert message in err
    assert path.read_bytes() == before


@pytest.mark.parametrize(
    ("poses", "message"),
    [
        ({2: np.eye(3)}, r"poses\[2\]: scan 2 is older than the journal"),
        ({13: np.eye(3)}, r"poses: scan 13 is not in the map"),
        ({6: np.diag([1.0, -1.0, 1.0])}, r"poses\[6\] is not rigid"),
        ({6: np.full((3, 3), np.nan)}, r"poses\[6\] contains NaN"),
        ({6: pose(1e6, 0.0, 0.0)}, r"poses\[6\] moves the scan out of the map"),
    ],
)
def test_bad_poses_are_refused_and_leave_the_map_unchanged(
    poses: dict[int, np.ndarray], message: str
) -> None:
    m = OnlineMap(config(journal_scans=5))
    m.insert_scans(posed_mission()[0])
    before = snapshot(m)
    journal = [s.points.tobytes() for s in m.scans()]
    with pytest.raises(OctolgpError, match=message):
        m.correct_poses(poses)
    assert snapshot(m) == before
    assert [s.points.tobytes() for s in m.scans()] == journal


def test_scans_without_a_rotation_cannot_take_absolute_poses(tmp_path: Path) -> None:
    """Scans made from points alone, and map files from before version 7, keep no rotation:
    ``correct_poses`` says so; ``correct_scans`` still works, and the file gains the column."""
    scans = [journaled(office_scan((0.0, 0.0))), journaled(office_scan((0.5, 0.2)))]
    path = tmp_path / "m.octolgp"
    with OnlineMap(config(), path=path) as m:
        m.insert_scans(scans)
        with pytest.raises(OctolgpError, match=r"poses\[2\]: scan 2 was journaled without its"):
            m.correct_poses({2: pose(0.5, 0.2, 0.0)})
    con = sqlite3.connect(path)  # as version 6 wrote it
    con.execute("ALTER TABLE scans DROP COLUMN rotation")
    con.execute("UPDATE meta SET value = '6' WHERE key = 'version'")
    con.commit()
    con.close()
    with OnlineMap.open(path) as back:
        before = snapshot(back)
        with pytest.raises(OctolgpError, match="without its sensor rotation"):
            back.correct_poses({2: pose(0.5, 0.2, 0.0)})
        assert snapshot(back) == before
        back.correct_scans({2: pose(0.05, 0.0, 0.0)})
        back.insert_scan(posed_scan(1.0, 0.0, 0.2))
        back.correct_poses({3: pose(1.0, 0.05, 0.2)})  # a new scan keeps its rotation


def test_the_journal_keeps_rotations_bit_for_bit(tmp_path: Path) -> None:
    scans = posed_mission()[0]
    with OnlineMap(config(), path=tmp_path / "m.octolgp") as m:
        m.insert_scans(scans)
    in_ram = OnlineMap(config())
    in_ram.insert_scans(scans)
    with OnlineMap.open(tmp_path / "m.octolgp", read_only=True) as back:
        for a, b, s in zip(back.scans(), in_ram.scans(), scans, strict=True):
            assert s.rotation is not None
            assert a.rotation is not None
            assert b.rotation is not None
            assert a.rotation.tobytes() == b.rotation.tobytes() == s.rotation.tobytes()
    con = sqlite3.connect(tmp_path / "m.octolgp")  # the checksum covers the rotation
    con.execute("UPDATE scans SET rotation = ? WHERE idx = 3", (np.eye(2).tobytes(),))
    con.commit()
    con.close()
    with (
        OnlineMap.open(tmp_path / "m.octolgp") as back,
        pytest.raises(OctolgpError, match="journaled scan 3 fails its checksum"),
    ):
        back.correct_poses({3: pose(0.0, 0.0, 0.0)})


def test_a_sensor_rotation_is_kept_as_the_nearest_rotation() -> None:
    R = planar_rotation(0.4, 3)
    printed = np.round(R, 4)  # a pose file's few digits
    got = nearest_rotation(printed, 3, "R")
    np.testing.assert_allclose(got.T @ got, np.eye(3), rtol=0, atol=1e-14)
    np.testing.assert_allclose(got, R, rtol=0, atol=1e-4)
    assert nearest_rotation(got, 3, "R").tobytes() == got.tobytes()  # kept bit for bit
    for bad, message in [
        (np.diag([1.0, 1.0, -1.0]), "is not a rotation"),
        (1.01 * R, "is not a rotation"),
        (np.eye(2), r"must have shape \(3, 3\)"),
        (np.full((3, 3), np.inf), "contains NaN or inf"),
    ]:
        with pytest.raises(OctolgpError, match=message):
            Scan([0.0, 0.0, 0.0], [[1.0, 0.0, 0.0]], rotation=bad)


def test_readers_keep_the_sensor_rotation() -> None:
    from types import SimpleNamespace

    s = Scan.from_ranges([1.0, 2.0, 0.5], [1.0, 2.0], [0.0, 0.1])
    assert s.pose is not None
    np.testing.assert_allclose(s.pose, pose(1.0, 2.0, 0.5), rtol=0, atol=1e-15)
    msg = SimpleNamespace(
        angle_min=0.0, angle_increment=0.1, ranges=[1.0, 2.0], range_min=0.1, range_max=5.0
    )
    T = np.eye(4)
    T[:3, :3] = planar_rotation(0.3, 3)
    T[:3, 3] = [1.0, 2.0, 3.0]
    laser = Scan.from_laserscan(msg, T)
    assert laser.pose is not None
    np.testing.assert_allclose(laser.pose, T, rtol=0, atol=1e-15)
    moved = transform_scan(laser, T)
    assert moved.pose is not None
    np.testing.assert_allclose(moved.pose, T @ T, rtol=0, atol=1e-12)
    rounded = laser.rounded(0.01)
    assert rounded.rotation is not None
    assert rounded.rotation.tobytes() == laser.rotation.tobytes()  # type: ignore[union-attr]


def test_an_npz_log_keeps_the_sensor_rotations(tmp_path: Path) -> None:
    from octolgp import load_scans
    from octolgp.io.npz import write_npz

    scans = posed_mission()[0]
    bare = Scan(scans[0].origin, scans[0].points, scans[0].max_range)
    write_npz(tmp_path / "log.npz", [bare, *scans[1:]])
    back = list(load_scans(tmp_path / "log.npz"))
    assert back[0].rotation is None
    for got, want in zip(back[1:], scans[1:], strict=True):
        assert got.rotation is not None
        assert want.rotation is not None
        assert got.rotation.tobytes() == want.rotation.tobytes()
    arrays = dict(np.load(tmp_path / "log.npz"))
    arrays["rotations"][3] = np.diag([1.0, -1.0])  # a reflection
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(OctolgpError, match=r"'rotations' row 3 is not a rotation"):
        load_scans(tmp_path / "bad.npz")
