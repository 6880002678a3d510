"""Pose corrections: ``OnlineMap.correct_scans`` equals a fresh build from the corrected scans."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_online import HP, assert_same_map, snapshot

from octolgp import MapConfig, OctolgpError, OnlineConfig, OnlineMap, Scan
from octolgp.mapping.correction import check_transform, transform_scan


def pose(x: float, y: float, yaw: float) -> np.ndarray:
    """A 2D rigid transform as a 3 x 3 homogeneous matrix."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def office_scan(origin: tuple[float, float], n: int = 120) -> Scan:
    """A scan in a 8 m square room with a 1 m pillar at (1.5, 1), 10 m no-returns capped."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    d = np.c_[np.cos(ang), np.sin(ang)]
    o = np.asarray(origin, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.min(np.where(d != 0, (np.sign(d) * 4.0 - o) / d, np.inf), axis=1)
        lo, hi = np.array([1.0, 0.5]) - o, np.array([2.0, 1.5]) - o
        t0 = np.where(d != 0, np.minimum(lo / d, hi / d), -np.inf).max(axis=1)
        t1 = np.where(d != 0, np.maximum(lo / d, hi / d), np.inf).min(axis=1)
    t = np.where((t0 <= t1) & (t0 > 0), np.minimum(t, t0), t)
    t[::17] = 6.0  # a few no-returns
    return Scan(origin=o, points=o + t[:, None] * d, max_range=6.0)


def drifted_mission() -> tuple[list[Scan], dict[int, np.ndarray]]:
    """12 scans around the room; from scan 6 on, odometry drifts; the corrections undo it."""
    truth = [
        office_scan((2.0 * np.cos(a) - 0.5, 2.0 * np.sin(a) - 1.0)) for a in np.linspace(0, 5, 12)
    ]
    scans, corrections = [], {}
    for i, s in enumerate(truth, start=1):
        if i < 6:
            scans.append(journaled(s))
            continue
        drift = pose(0.04 * (i - 5), -0.03 * (i - 5), 0.01 * (i - 5))
        scans.append(journaled(transform_scan(s, drift)))
        corrections[i] = np.linalg.inv(drift)
    return scans, corrections


def journaled(scan: Scan) -> Scan:
    """A scan as the map keeps it (rounded to ``OnlineConfig.scan_precision``): a
    correction moves what the map was built from."""
    precision = OnlineConfig().scan_precision
    assert precision is not None
    return scan.rounded(precision)


def config(engine: str = "lattice") -> MapConfig:
    return MapConfig(dim=2, resolution=0.1, hyperparameters=HP, online=OnlineConfig(engine=engine))


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_a_correction_equals_a_fresh_build_from_the_corrected_scans(
    tmp_path: Path, engine: str
) -> None:
    scans, corrections = drifted_mission()
    with OnlineMap(config(engine), path=tmp_path / "m.octolgp") as m:
        m.insert_scans(scans)
        update = m.correct_scans(corrections)
        corrected = [
            journaled(transform_scan(s, corrections[i])) if i in corrections else s
            for i, s in enumerate(scans, start=1)
        ]
        fresh = OnlineMap(config(engine))
        fresh.insert_scans(corrected)
        assert_same_map(m, fresh)
        assert (
            0 < update.refit_leaves <= update.touched_leaves <= len(m.store) + update.removed_leaves
        )
        # the journal holds the corrected scans
        for got, want in zip(m.scans(), corrected, strict=True):
            np.testing.assert_array_equal(got.points, want.points)
            np.testing.assert_array_equal(got.origin, want.origin)
    with OnlineMap.open(tmp_path / "m.octolgp") as back:  # and so does the file
        assert_same_map(back, fresh)
        back.insert_scan(office_scan((0.0, 0.0)))  # mapping goes on from the corrected map
        fresh.insert_scan(office_scan((0.0, 0.0)))
        assert_same_map(back, fresh)


def test_a_correction_that_moves_a_scan_away_removes_the_leaves_it_made(tmp_path: Path) -> None:
    scans = [journaled(office_scan((0.0, 0.0))), journaled(office_scan((0.5, 0.0)))]
    far = Scan(origin=[30.0, 30.0], points=[[31.0, 30.0], [30.0, 31.5]])
    with OnlineMap(config(), path=tmp_path / "m.octolgp") as m:
        m.insert_scans([*scans, far])
        n = len(m.store)
        update = m.correct_scans({3: pose(-30.0, -30.0, 0.0)})  # the stray scan comes home
        assert update.removed_leaves > 0
        assert len(m.store) < n
        fresh = OnlineMap(config())
        fresh.insert_scans([*scans, transform_scan(far, pose(-30.0, -30.0, 0.0))])
        assert_same_map(m, fresh)


@pytest.mark.parametrize("in_ram", [False, True])
def test_a_correction_while_learning_moves_the_buffered_scans(tmp_path: Path, in_ram: bool) -> None:
    """In RAM the lattice map keeps the buffered scans' evidence while it learns: the
    correction rebuilds it too."""
    learning = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=5))
    scans, _ = drifted_mission()
    with OnlineMap(learning, path=None if in_ram else tmp_path / "m.octolgp") as m:
        m.insert_scans(scans[:3])
        update = m.correct_scans({2: pose(0.1, 0.0, 0.02)})
        assert update.buffered
        moved = journaled(transform_scan(scans[1], pose(0.1, 0.0, 0.02)))
        np.testing.assert_array_equal(list(m.scans())[1].points, moved.points)
        m.insert_scans(scans[3:6])
        fresh = OnlineMap(learning)
        fresh.insert_scans([scans[0], moved, *scans[2:6]])
        assert m.hyperparameters == fresh.hyperparameters
        assert_same_map(m, fresh)


@pytest.mark.parametrize(
    ("corrections", "message"),
    [
        ({0: np.eye(3)}, "scan 0 is not in the map"),
        ({13: np.eye(3)}, "scan 13 is not in the map"),
        ({"3": np.eye(3)}, "scan number '3' is not an integer"),
        ({3: np.eye(4)}, r"corrections\[3\] must have shape \(3, 3\)"),
        ({3: np.full((3, 3), np.nan)}, r"corrections\[3\] contains NaN"),
        ({3: np.diag([2.0, 2.0, 1.0])}, r"corrections\[3\] is not rigid"),
        ({3: np.diag([1.0, -1.0, 1.0])}, r"corrections\[3\] is not rigid"),  # a reflection
        ({3: [[1, 0.2, 0], [0, 1, 0], [0, 0, 1]]}, r"corrections\[3\] is not rigid"),  # shear
        ({3: [[1, 0, 0], [0, 1, 0], [0.1, 0, 1]]}, r"corrections\[3\] must end with"),
        ({3: np.eye(3), 5: "x"}, r"corrections\[5\] is not a numeric matrix"),
        ([np.eye(3)], "must be a mapping"),
        ({4: pose(1e6, 0.0, 0.0)}, r"corrections\[4\] moves the scan out of the map"),
    ],
)
def test_bad_corrections_are_refused_and_leave_the_map_unchanged(
    tmp_path: Path, corrections: object, message: str
) -> None:
    scans, _ = drifted_mission()
    with OnlineMap(config(), path=tmp_path / "m.octolgp") as m:
        m.insert_scans(scans)
        before = snapshot(m)
        journal = [s.points.tobytes() for s in m.scans()]
        with pytest.raises(OctolgpError, match=message):
            m.correct_scans(corrections)  # type: ignore[arg-type]
        assert snapshot(m) == before
        assert [s.points.tobytes() for s in m.scans()] == journal


@pytest.mark.parametrize("engine", ["lattice", "exact"])
def test_a_map_in_memory_corrects_as_a_map_file_does(tmp_path: Path, engine: str) -> None:
    """The journal of a map without a file is kept in RAM: the same correction, bit for bit."""
    scans, corrections = drifted_mission()
    with OnlineMap(config(engine), path=tmp_path / "m.octolgp") as on_disk:
        in_ram = OnlineMap(config(engine))
        for m in (on_disk, in_ram):
            m.insert_scans(scans)
            m.correct_scans(corrections)
        assert in_ram.path is None
        assert snapshot(in_ram) == snapshot(on_disk)
        for a, b in zip(in_ram.scans(), on_disk.scans(), strict=True):  # the same journal
            assert a.points.tobytes() == b.points.tobytes()
            assert a.origin.tobytes() == b.origin.tobytes()
        assert 0 < in_ram.journal_bytes < 16 * sum(len(s) for s in scans)
        assert on_disk.journal_bytes == 0


def test_a_budgeted_map_corrects_through_its_spill_file() -> None:
    scans, corrections = drifted_mission()
    budget = MapConfig(dim=2, resolution=0.1, hyperparameters=HP, memory_budget_mb=0.3)
    m = OnlineMap(budget)
    m.insert_scans(scans)
    m.correct_scans(corrections)
    fresh = OnlineMap(config())
    fresh.insert_scans(
        [
            transform_scan(s, corrections[i]) if i in corrections else s
            for i, s in enumerate(scans, 1)
        ]
    )
    assert_same_map(m, fresh)


def test_check_transform_accepts_rotations_in_3d() -> None:
    angle = 0.7
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(check_transform(T, 3, "T"), T)


CHILD = """
import sys
sys.path.insert(0, sys.argv[2])
from test_correct import config, drifted_mission
from octolgp import OnlineMap
m = OnlineMap.open(sys.argv[1])
_, corrections = drifted_mission()
print("correcting", flush=True)
m.correct_scans(corrections)
print("done", flush=True)
sys.stdin.readline()
"""


@pytest.mark.parametrize("delay", [0.0, 0.05, 0.2])
def test_a_killed_correction_reopens_before_or_after(tmp_path: Path, delay: float) -> None:
    scans, corrections = drifted_mission()
    path = tmp_path / "m.octolgp"
    with OnlineMap(config(), path=path) as m:
        m.insert_scans(scans)
        before = snapshot(m)
    after_map = OnlineMap(config())
    after_map.insert_scans(
        [
            transform_scan(s, corrections[i]) if i in corrections else s
            for i, s in enumerate(scans, 1)
        ]
    )
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), str(Path(__file__).parent)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "correcting"
    if delay:
        import time

        time.sleep(delay)
    child.kill()  # SIGKILL: no cleanup in the child
    child.wait()
    for stream in (child.stdout, child.stdin):
        if stream is not None:
            stream.close()
    with OnlineMap.open(path) as back:
        if snapshot(back) != before:  # then it must be the whole correction
            assert_same_map(back, after_map)
        back.insert_scan(office_scan((0.0, 0.0)))  # and the file is usable either way


# ---------------------------------------------------------------- the command line
def _write_map(path: Path) -> dict[int, np.ndarray]:
    scans, corrections = drifted_mission()
    with OnlineMap(config(), path=path) as m:
        m.insert_scans(scans)
    return corrections


def test_octolgp_correct_applies_a_corrections_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from octolgp.cli.main import main
    from octolgp.io.corrections import read_corrections

    path = tmp_path / "m.octolgp"
    corrections = _write_map(path)
    lines = ["# scan, then the matrix row by row or x y yaw"]
    for i, T in corrections.items():
        if i % 2:  # odd scans as a pose, even ones as a matrix
            yaw = float(np.arctan2(T[1, 0], T[0, 0]))
            lines.append(f"{i} {float(T[0, 2])!r} {float(T[1, 2])!r} {yaw!r}")
        else:
            lines.append(f"{i}  " + " ".join(repr(float(v)) for v in T.ravel()) + "  # a matrix")
    poses = tmp_path / "poses.txt"
    poses.write_text("\n".join(lines) + "\n\n")
    assert main(["correct", str(path), "--poses", str(poses)]) == 0
    assert "corrected 7 scans" in capsys.readouterr().out
    read = read_corrections(poses, 2)
    assert read.keys() == corrections.keys()
    for i, T in corrections.items():  # the text holds the transforms to rounding
        np.testing.assert_allclose(read[i], T, rtol=0, atol=1e-12)
    scans, _ = drifted_mission()
    fresh = OnlineMap(config())
    fresh.insert_scans(
        [transform_scan(s, read[i]) if i in read else s for i, s in enumerate(scans, 1)]
    )
    with OnlineMap.open(path) as back:  # the map the file's transforms make
        assert_same_map(back, fresh)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("6 0.1 0.0\n", "poses.txt:1: scan 6: expected 3 values (a pose), 6 or 9"),
        ("# fine\n6 0.1 0.0 zero\n", "poses.txt:2: a value is not a number"),
        ("x 0.1 0.0 0.0\n", "poses.txt:1: scan number 'x' is not a positive integer"),
        ("6 0 0 0\n6 0 0 0\n", "poses.txt:2: scan 6 is corrected twice"),
        ("6 2 0 0 0 2 0 0 0 1\n", "poses.txt:1: scan 6 is not rigid"),
        ("99 0 0 0\n", "poses.txt:1: scan 99 is not in the map"),
    ],
)
def test_octolgp_correct_refuses_a_bad_file_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    from octolgp.cli.main import main

    path = tmp_path / "m.octolgp"
    _write_map(path)
    with OnlineMap.open(path) as m:
        before = snapshot(m)
    poses = tmp_path / "poses.txt"
    poses.write_text(text)
    assert main(["correct", str(path), "--poses", str(poses)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.startswith("octolgp: error:")
    assert message in err
    with OnlineMap.open(path) as m:
        assert snapshot(m) == before


def test_a_3d_pose_line_is_a_rotation_and_a_translation() -> None:
    from octolgp.io.corrections import pose_matrix

    half = np.sqrt(0.5)
    T = pose_matrix(np.array([1.0, 2.0, 3.0, 0.0, 0.0, half, half]), 3)  # 90° about z
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_array_equal(T[:3, 3], [1.0, 2.0, 3.0])


def test_corrections_between_inserts_keep_the_scan_index_current(tmp_path: Path) -> None:
    scans, corrections = drifted_mission()
    with OnlineMap(config(), path=tmp_path / "m.octolgp") as m:
        m.insert_scans(scans[:8])
        m.correct_scans({6: corrections[6], 7: corrections[7]})
        m.insert_scans(scans[8:])
        m.correct_scans({i: corrections[i] for i in (8, 9, 10, 11, 12)})
        m.correct_scans({3: pose(0.02, 0.0, 0.0)})
        final = [
            transform_scan(s, corrections[i]) if i in corrections else s
            for i, s in enumerate(scans, 1)
        ]
        final[2] = transform_scan(final[2], pose(0.02, 0.0, 0.0))
        fresh = OnlineMap(config())
        fresh.insert_scans(final)
        assert_same_map(m, fresh)


def test_a_map_made_without_a_journal_cannot_be_corrected() -> None:
    m = OnlineMap(config(), journal=False)
    m.insert_scans(drifted_mission()[0][:3])
    assert m.journal_bytes == 0
    before = snapshot(m)
    with pytest.raises(OctolgpError, match=r"keeps no journal.*journal=False"):
        m.correct_scans({2: pose(0.1, 0.0, 0.0)})
    assert snapshot(m) == before


def test_a_map_saved_from_memory_keeps_its_journal(tmp_path: Path) -> None:
    m = OnlineMap(config())
    m.insert_scans(drifted_mission()[0][:4])
    m.save(tmp_path / "saved.octolgp")
    m.correct_scans({2: pose(0.1, 0.0, 0.0)})
    with OnlineMap.open(tmp_path / "saved.octolgp") as back:
        back.correct_scans({2: pose(0.1, 0.0, 0.0)})
        assert snapshot(back) == snapshot(m)


def test_a_map_file_without_a_journal_cannot_be_corrected(tmp_path: Path) -> None:
    """Earlier versions saved a map in memory without its scans."""
    import sqlite3

    m = OnlineMap(config())
    m.insert_scans(drifted_mission()[0][:4])
    m.save(tmp_path / "saved.octolgp")
    con = sqlite3.connect(tmp_path / "saved.octolgp")
    con.execute("DELETE FROM scans")
    con.commit()
    con.close()
    with OnlineMap.open(tmp_path / "saved.octolgp") as back:
        before = snapshot(back)
        with pytest.raises(OctolgpError, match="no journal"):
            back.correct_scans({2: pose(0.1, 0.0, 0.0)})
        assert snapshot(back) == before
