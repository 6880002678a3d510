"""KITTI odometry reader: the bundled simulated-street fixture, exact frames, malformed input."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.cli import main
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import KittiReader, detect_format, load_scans, read_kitti
from octolgp.io.kitti import looks_like_kitti, read_kitti_calib, read_kitti_poses

DATA = Path(__file__).parent / "data" / "kitti"
SEQUENCE = DATA / "sequences" / "00"
HEIGHT = 1.73  # the fixture's sensor height above the road, metres
HP = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=3.0)


def _rigid(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


def _line(M: np.ndarray) -> str:
    return " ".join(f"{v:.12e}" for v in M[:3].ravel())


def _write_sequence(root: Path, points: list[np.ndarray], poses: list[np.ndarray]) -> Path:
    """A KITTI layout under ``root``: ``sequences/07`` with these Velodyne points and poses."""
    seq = root / "sequences" / "07"
    (seq / "velodyne").mkdir(parents=True)
    (root / "poses").mkdir()
    for i, xyz in enumerate(points):
        rec = np.column_stack([xyz, np.ones(len(xyz))]).astype("<f4")
        (seq / "velodyne" / f"{i:06d}.bin").write_bytes(rec.tobytes())
    tr = _rigid(-np.pi / 2, (0.1, -0.2, -0.3))
    (seq / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {_line(tr)}\n")
    (root / "poses" / "07.txt").write_text("".join(_line(P) + "\n" for P in poses))
    return seq


def test_fixture_is_guessed_and_forced() -> None:
    assert detect_format(SEQUENCE) == "kitti"
    guessed = list(load_scans(SEQUENCE))
    forced = list(load_scans(SEQUENCE, format="kitti"))
    assert len(guessed) == len(forced) == 5
    for a, b in zip(guessed, forced, strict=True):
        assert a.dim == 3
        assert 300 <= len(a) <= 400
        assert a.max_range is None
        np.testing.assert_array_equal(a.points, b.points)
    assert sum(f.stat().st_size for f in DATA.rglob("*") if f.is_file()) < 200_000


def test_world_frames_and_origins() -> None:
    reader = read_kitti(SEQUENCE, world="cam0")
    cam0 = list(reader)
    velo = list(read_kitti(SEQUENCE))  # the default: the Velodyne's frame, z up
    Tr = reader.calibration
    np.testing.assert_allclose(Tr, read_kitti_calib(SEQUENCE / "calib.txt"))
    poses = read_kitti_poses(DATA / "poses" / "00.txt")
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)  # P_0 = I, as in KITTI
    for i, (c, v) in enumerate(zip(cam0, velo, strict=True)):
        # cam0 world = Tr (velodyne world); origin = P_i Tr 0
        np.testing.assert_allclose(c.points, v.points @ Tr[:3, :3].T + Tr[:3, 3], atol=1e-9)
        np.testing.assert_allclose(c.origin, (poses[i] @ Tr)[:3, 3], atol=1e-12)
        np.testing.assert_allclose(c.origin, reader.transforms[i][:3, 3])
    np.testing.assert_allclose(velo[0].origin, 0.0, atol=1e-9)
    # The street in the Velodyne's frame 0: road at -HEIGHT, house fronts at |y| = 6 m.
    pts = np.concatenate([s.points for s in velo])
    assert pts[:, 2].min() > -HEIGHT - 1e-4
    assert np.abs(pts[:, 1]).max() < 6.0 + 1e-4
    on_road = np.abs(pts[:, 2] + HEIGHT) < 1e-4
    on_walls = np.abs(np.abs(pts[:, 1]) - 6.0) < 1e-4
    assert on_road.mean() > 0.3
    assert on_walls.sum() > 100


def test_points_are_posed_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    points = [rng.uniform(-10, 10, (50, 3)).astype(np.float32).astype(np.float64) for _ in "ab"]
    poses = [np.eye(4), _rigid(0.3, (1.0, 2.0, 3.0))]
    seq = _write_sequence(tmp_path, points, poses)
    scans = list(load_scans(seq))
    Tr = _rigid(-np.pi / 2, (0.1, -0.2, -0.3))
    for scan, xyz, P in zip(scans, points, poses, strict=True):
        T = np.linalg.inv(Tr) @ P @ Tr  # the Velodyne's frame at frame 0 (the default)
        np.testing.assert_allclose(scan.points, xyz @ T[:3, :3].T + T[:3, 3], atol=1e-9)
        np.testing.assert_allclose(scan.origin, T[:3, 3], atol=1e-12)
    # poses= elsewhere; frames numbered from a file name, not a count
    other = tmp_path / "elsewhere.txt"
    shutil.move(tmp_path / "poses" / "07.txt", other)
    (seq / "velodyne" / "000000.bin").unlink()
    reader = KittiReader(seq, poses=other, max_range=80.0)
    assert reader.frames == (1,)
    (only,) = list(reader)
    np.testing.assert_allclose(only.points, scans[1].points)
    assert only.max_range == 80.0


def test_fixture_maps_the_street() -> None:
    scans = list(read_kitti(SEQUENCE, world="velodyne"))
    m = OnlineMap(MapConfig(dim=3, resolution=0.4, hyperparameters=HP))
    m.insert_scans(scans)
    hits = np.concatenate([s.points for s in scans])
    assert np.median(m.occupancy(hits)) > 0.6
    path = np.column_stack([np.linspace(0.5, 3.5, 20), np.zeros(20), np.zeros(20)])
    assert m.occupancy(path).max() < 0.4  # the air the car drove through


def _copy_fixture(tmp_path: Path) -> Path:
    shutil.copytree(DATA, tmp_path / "kitti")
    return tmp_path / "kitti" / "sequences" / "00"


def _edit(name: str, line: int, text: str | None) -> Callable[[Path], None]:
    """Replace (or with ``None`` delete) line ``line`` (1-based) of ``calib.txt`` or the poses."""

    def apply(seq: Path) -> None:
        f = seq / "calib.txt" if name == "calib" else seq.parent.parent / "poses" / "00.txt"
        lines = f.read_text().splitlines()
        if text is None:
            del lines[line - 1]
        else:
            lines[line - 1] = text
        f.write_text("\n".join(lines) + "\n")

    return apply


@pytest.mark.parametrize(
    ("corrupt", "message"),
    [
        (_edit("calib", 2, "P1 1 2 3"), "calib.txt:2: expected 'KEY: numbers'"),
        (_edit("calib", 3, "P2: 1 2 x"), "calib.txt:3: P2: non-numeric"),
        (_edit("calib", 5, "Tr: " + " ".join(["0"] * 11)), "calib.txt:5: Tr needs 12 numbers"),
        (_edit("calib", 5, "Tr: " + " ".join(["2"] * 12)), "calib.txt:5: Tr's 3 x 3 part"),
        (_edit("calib", 5, None), "calib.txt: no 'Tr:' line"),
        (_edit("poses", 3, "1 0 0 0 0 1 0 0 0 0 1"), "00.txt:3: expected 12 numbers"),
        (_edit("poses", 2, "1 0 0 0 0 1 0 0 0 0 1 zero"), "00.txt:2: non-numeric"),
        (_edit("poses", 4, "1 0 0 0 0 1 0 0 0 0 1 nan"), "00.txt:4: NaN or inf"),
        (_edit("poses", 2, "2 0 0 0 0 1 0 0 0 0 1 0"), "00.txt:2: the 3 x 3 part is not"),
        (_edit("poses", 5, None), "00.txt:5: no pose for frame 4"),
        (_edit("poses", 2, ""), "00.txt:2: expected 12 numbers"),
    ],
)
def test_malformed_calib_and_poses_name_file_and_line(
    tmp_path: Path, corrupt: Callable[[Path], None], message: str
) -> None:
    seq = _copy_fixture(tmp_path)
    corrupt(seq)
    with pytest.raises(OctolgpError, match="KITTI") as exc:
        read_kitti(seq)
    assert message in str(exc.value)
    assert str(seq.parent.parent) in str(exc.value)


def test_malformed_scans_raise_or_are_skipped(tmp_path: Path) -> None:
    seq = _copy_fixture(tmp_path)
    bad_size = seq / "velodyne" / "000002.bin"
    bad_size.write_bytes(bad_size.read_bytes()[:-5])
    with pytest.raises(OctolgpError, match=r"000002\.bin: byte \d+: size \d+ is not a multiple"):
        list(read_kitti(seq))
    nan = seq / "velodyne" / "000001.bin"
    rec = np.frombuffer(nan.read_bytes(), dtype="<f4").copy()
    rec[4 * 3 + 1] = np.nan  # point 3's y
    nan.write_bytes(rec.tobytes())
    reader = read_kitti(seq)
    next(reader)
    with pytest.raises(OctolgpError, match=r"000001\.bin:point 3: NaN or inf"):
        next(reader)
    skipping = read_kitti(seq, skip_bad=True)
    scans = list(skipping)
    assert len(scans) == 4
    assert skipping.skipped == 2
    assert skipping.bad_lines == [(nan, 3)]
    assert "000002.bin" in skipping.bad_scans[0]


def test_missing_files_and_bad_arguments(tmp_path: Path) -> None:
    seq = _copy_fixture(tmp_path)
    with pytest.raises(OctolgpError, match="world must be one of"):
        read_kitti(seq, world="cam2")
    shutil.copytree(seq, seq.parent / "01")
    with pytest.raises(MapFileNotFound, match=r"poses/01\.txt"):
        read_kitti(seq.parent / "01")
    (seq / "calib.txt").unlink()
    with pytest.raises(MapFileNotFound, match=r"calib\.txt"):
        read_kitti(seq)
    empty = tmp_path / "empty"
    (empty / "velodyne").mkdir(parents=True)
    (empty / "calib.txt").write_text((DATA / "sequences" / "00" / "calib.txt").read_text())
    with pytest.raises(OctolgpError, match=r"no velodyne/NNNNNN\.bin"):
        read_kitti(empty)
    assert not looks_like_kitti(SEQUENCE / "velodyne")
    assert not looks_like_kitti(SEQUENCE / "calib.txt")


def test_cli_bad_kitti_sequence_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = _copy_fixture(tmp_path)
    _edit("poses", 3, "1 2 3")(seq)
    assert main(["run", str(seq), "--out", str(tmp_path / "m.octolgp"), "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("octolgp: error: KITTI poses")
    assert "00.txt:3: expected 12 numbers" in lines[0]
    assert not (tmp_path / "m.octolgp").exists()
