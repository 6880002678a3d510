"""Scan-log readers and writers: npz round trip, CARMEN on the real Intel log, errors."""

from __future__ import annotations

import gzip
import logging
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import (
    CarmenReader,
    detect_format,
    load_scans,
    read_carmen,
    read_truth,
    save_scan_log,
)
from octolgp.io.carmen import NO_RETURN_MARGIN, beam_angles
from octolgp.scan import Scan
from octolgp.sim.scenes import simulate_paper2d

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"
FIRST20 = ROOT / "tests" / "data" / "intel_first20.log"


def _lengths(scan: Scan) -> np.ndarray:
    return np.asarray(np.linalg.norm(scan.points - scan.origin, axis=1))


def _max_ranges(scans: Iterable[Scan]) -> np.ndarray:
    return np.array([np.nan if s.max_range is None else s.max_range for s in scans])


def _no_returns(scan: Scan) -> int:
    assert scan.max_range is not None
    return int((_lengths(scan) >= scan.max_range).sum())


# --------------------------------------------------------------------------- npz


def test_npz_round_trip_with_truth(tmp_path: Path) -> None:
    data = simulate_paper2d(seed=0)
    path = tmp_path / "paper.npz"
    save_scan_log(path, data.scans, data.truth_points, data.truth_labels)
    assert detect_format(path) == "npz"
    loaded = list(load_scans(path))
    assert len(loaded) == len(data.scans)
    for a, b in zip(loaded, data.scans, strict=True):
        np.testing.assert_array_equal(a.origin, b.origin)
        np.testing.assert_array_equal(a.points, b.points)
        assert a.max_range == b.max_range
        assert a.stamp == b.stamp
    points, labels = read_truth(path)
    np.testing.assert_array_equal(points, data.truth_points)
    np.testing.assert_array_equal(labels, data.truth_labels)
    assert labels.dtype == np.int8
    with np.load(path) as npz:
        assert npz["offsets"].dtype == np.int64
        assert npz["offsets"].shape == (29,)


@given(
    st.lists(st.tuples(st.integers(1, 6), st.booleans(), st.booleans()), min_size=1, max_size=5),
    st.sampled_from([2, 3]),
)
def test_npz_round_trip_property(specs: list[tuple[int, bool, bool]], d: int) -> None:
    import tempfile

    rng = np.random.default_rng(len(specs) * 10 + d)
    scans = [
        Scan(rng.normal(size=d), rng.normal(size=(n, d)), 5.0 if mr else None, 1.5 if stp else None)
        for n, mr, stp in specs
    ]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.npz"
        save_scan_log(path, scans)
        loaded = list(load_scans(path))
    assert len(loaded) == len(scans)
    for a, b in zip(loaded, scans, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.origin, b.origin)
        assert (a.max_range, a.stamp) == (b.max_range, b.stamp)


def _write_npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)  # type: ignore[arg-type]
    return path


GOOD = {
    "origins": np.zeros((2, 2)),
    "points": np.ones((5, 2)),
    "offsets": np.array([0, 2, 5]),
}


@pytest.mark.parametrize(
    ("change", "array"),
    [
        ({"offsets": np.array([0, 3, 2])}, "offsets"),  # not monotone
        ({"offsets": np.array([0, 2, 4])}, "offsets"),  # does not end at N
        ({"offsets": np.array([1, 2, 5])}, "offsets"),  # does not start at 0
        ({"offsets": np.array([0, 0, 5])}, "offsets"),  # empty scan
        ({"offsets": np.array([0.0, 2.0, 5.0])}, "offsets"),  # not integers
        ({"points": np.ones((5, 3))}, "points"),  # dimension mismatch
        ({"origins": np.zeros((2, 4))}, "origins"),  # d not 2 or 3
        ({"points": np.full((5, 2), np.nan)}, "points"),
        ({"max_range": np.ones(3)}, "max_range"),  # wrong length
        ({"max_range": np.array([1.0, -1.0])}, "max_range"),
        ({"stamps": np.zeros((2, 1))}, "stamps"),
    ],
)
def test_npz_validation_names_array_and_file(
    tmp_path: Path, change: dict[str, np.ndarray], array: str
) -> None:
    path = _write_npz(tmp_path / "bad.npz", **{**GOOD, **change})
    with pytest.raises(OctolgpError, match=array) as info:
        load_scans(path)  # raises at the call, before iteration
    assert "bad.npz" in str(info.value)


@pytest.mark.parametrize("missing", ["origins", "points", "offsets"])
def test_npz_missing_array(tmp_path: Path, missing: str) -> None:
    arrays = {k: v for k, v in GOOD.items() if k != missing}
    path = _write_npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(OctolgpError, match=f"{missing}.*missing"):
        load_scans(path)


def test_npz_read_truth_absent(tmp_path: Path) -> None:
    path = _write_npz(tmp_path / "log.npz", **GOOD)
    assert len(list(load_scans(path))) == 2
    with pytest.raises(OctolgpError, match="no ground truth"):
        read_truth(path)


def test_save_scan_log_rejects_bad_input(tmp_path: Path) -> None:
    s2 = Scan(np.zeros(2), np.ones((1, 2)))
    s3 = Scan(np.zeros(3), np.ones((1, 3)))
    with pytest.raises(OctolgpError, match=r"\.npz"):
        save_scan_log(tmp_path / "log.txt", [s2])
    with pytest.raises(OctolgpError, match="dimension"):
        save_scan_log(tmp_path / "log.npz", [s2, s3])
    with pytest.raises(OctolgpError, match="no scans"):
        save_scan_log(tmp_path / "log.npz", [])
    with pytest.raises(OctolgpError, match="together"):
        save_scan_log(tmp_path / "log.npz", [s2], truth_points=np.zeros((1, 2)))
    with pytest.raises(OctolgpError, match="truth_labels"):
        save_scan_log(tmp_path / "log.npz", [s2], np.zeros((2, 2)), np.array([0, 2]))


# ------------------------------------------------------------------ format choice


def test_missing_file_raises_at_call(tmp_path: Path) -> None:
    for name in ("nothing.npz", "nothing.log", "nothing.log.gz", "nothing"):
        with pytest.raises(MapFileNotFound):
            load_scans(tmp_path / name)  # not iterated: must raise at the call
    with pytest.raises(FileNotFoundError):
        load_scans(tmp_path / "nothing.clf")


def test_foreign_or_unknown_format_raises_at_call(tmp_path: Path) -> None:
    binary = tmp_path / "blob.bin"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(OctolgpError, match="unknown format"):
        load_scans(binary)
    fake_npz = tmp_path / "fake.npz"
    fake_npz.write_text("not a zip archive\n")
    with pytest.raises(OctolgpError, match=r"fake\.npz"):
        load_scans(fake_npz)
    prose = tmp_path / "notes.log"
    prose.write_text("2024-01-01 12:00 INFO started\n")
    with pytest.raises(OctolgpError, match="CARMEN"):
        load_scans(prose)
    bad_gzip = tmp_path / "broken.log.gz"
    bad_gzip.write_bytes(b"\x1f\x8b" + b"\x00" * 40)
    with pytest.raises(OctolgpError):
        load_scans(bad_gzip)
    with pytest.raises(OctolgpError, match="unknown format"):
        load_scans(FIRST20, format="las")
    with pytest.raises(OctolgpError, match="not a ROS bag"):
        load_scans(FIRST20, format="rosbag")
    with pytest.raises(OctolgpError, match="not a file"):
        load_scans(tmp_path)


def test_format_sniffed_from_content(tmp_path: Path) -> None:
    plain = tmp_path / "intel.txt"
    shutil.copy(FIRST20, plain)
    gz = tmp_path / "intel.dat"
    gz.write_bytes(gzip.compress(FIRST20.read_bytes()))
    assert detect_format(plain) == detect_format(gz) == "carmen"
    assert detect_format(FIRST20) == detect_format(INTEL) == "carmen"
    assert len(list(load_scans(gz))) == 20


# ------------------------------------------------------------------------ CARMEN


def test_beam_angles_conventions() -> None:
    a180 = beam_angles(180)
    assert a180[0] == -np.pi / 2
    assert np.isclose(a180[-1], np.deg2rad(89.0))
    assert np.isclose(beam_angles(360)[-1], np.deg2rad(89.5))
    for n in (181, 361, 100):
        a = beam_angles(n)
        assert a.shape == (n,)
        assert np.isclose(a[0], -np.pi / 2)
        assert np.isclose(a[-1], np.pi / 2)
    assert beam_angles(1).tolist() == [0.0]


def test_intel_full_log_matches_readme_counts() -> None:
    reader = load_scans(INTEL)
    assert isinstance(reader, CarmenReader)
    scans = list(reader)
    assert len(scans) == 910
    assert {len(s) for s in scans} == {180}
    assert reader.skipped == 0
    assert reader.no_return == pytest.approx(81.83)
    assert np.allclose(_max_ranges(scans), 81.83 - NO_RETURN_MARGIN)
    assert sum(_no_returns(s) for s in scans) == 4172
    lengths = np.concatenate([_lengths(s) for s in scans])
    valid = lengths[lengths < 81.8]
    assert valid.size == 159_628
    assert valid.min() == pytest.approx(0.23, abs=1e-6)
    assert valid.max() == pytest.approx(25.38, abs=1e-6)
    stamps = np.array([s.stamp for s in scans])
    assert stamps.min() == pytest.approx(32.907, abs=1e-3)
    assert stamps.max() == pytest.approx(2683.770, abs=1e-3)
    origins = np.stack([s.origin for s in scans])
    np.testing.assert_allclose(origins.min(axis=0), [-9.227, -22.125], atol=1e-3)
    np.testing.assert_allclose(origins.max(axis=0), [16.545, 3.899], atol=1e-3)


def test_intel_first20_fixture_matches_full_log() -> None:
    small = list(load_scans(FIRST20))
    full = [s for _, s in zip(range(20), load_scans(INTEL), strict=False)]
    assert len(small) == 20
    for a, b in zip(small, full, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.origin, b.origin)
        assert a.stamp == b.stamp
        assert a.max_range == b.max_range


def test_intel_first_scan_geometry() -> None:
    scan = next(load_scans(FIRST20))
    tokens = FIRST20.read_text().split("\nFLASER ", 1)[1].split()
    ranges = np.array(tokens[1:181], dtype=float)
    x, y, theta, stamp = (float(t) for t in (*tokens[181:184], tokens[187]))
    np.testing.assert_allclose(scan.origin, [x, y])
    assert scan.stamp == stamp
    np.testing.assert_allclose(_lengths(scan), ranges, atol=1e-9)
    # Beam 0 points at theta - 90 degrees (the robot's right), counter-clockwise after.
    bearing = np.arctan2(*(scan.points - scan.origin)[:, ::-1].T)
    expected = theta - np.pi / 2 + np.deg2rad(np.arange(180))
    np.testing.assert_allclose(np.angle(np.exp(1j * (bearing - expected))), 0.0, atol=1e-9)


def test_carmen_gzip_equals_plain(tmp_path: Path) -> None:
    gz = tmp_path / "first20.log.gz"
    gz.write_bytes(gzip.compress(FIRST20.read_bytes()))
    for a, b in zip(load_scans(gz), load_scans(FIRST20), strict=True):
        np.testing.assert_array_equal(a.points, b.points)


def test_carmen_max_range_sources(tmp_path: Path) -> None:
    explicit = list(read_carmen(FIRST20, max_range=50.0))
    assert np.allclose(_max_ranges(explicit), 50.0 - NO_RETURN_MARGIN)
    with_param = tmp_path / "param.log"
    with_param.write_text("PARAM robot_front_laser_max 80.99 nohost 0\n" + FIRST20.read_text())
    assert np.allclose(_max_ranges(read_carmen(with_param)), 80.99 - NO_RETURN_MARGIN)
    # No repeated maximum among the scans: no sentinel, every beam is a hit.
    lines = [ln for ln in FIRST20.read_text().splitlines() if ln.startswith("FLASER")]
    single = tmp_path / "single.log"
    tokens = lines[0].split()
    tokens[2:182] = [f"{1 + 0.01 * i:.2f}" for i in range(180)]
    single.write_text(" ".join(tokens) + "\n")
    scan = next(iter(read_carmen(single)))
    assert scan.max_range is None


def test_carmen_robotlaser1(tmp_path: Path) -> None:
    ranges = "1.0 2.0 10.0 3.0 4.0"
    line = (
        f"ROBOTLASER1 0 -0.785398 1.570796 0.392699 10.0 0.01 0 5 {ranges} "
        "2 0.5 0.5 1.0 2.0 0.5 0.9 1.9 0.5 0 0 0 0 0 12.5 host 12.5\n"
    )
    path = tmp_path / "robot.clf"
    path.write_text("# header\n" + line)
    (scan,) = list(load_scans(path))
    np.testing.assert_allclose(scan.origin, [1.0, 2.0])
    assert scan.stamp == 12.5
    assert scan.max_range == pytest.approx(10.0 - NO_RETURN_MARGIN)
    assert _no_returns(scan) == 1
    bearing = np.arctan2(*(scan.points - scan.origin)[:, ::-1].T)
    np.testing.assert_allclose(bearing, 0.5 - 0.785398 + 0.392699 * np.arange(5), atol=1e-9)


def _malformed(tmp_path: Path, kind: str) -> tuple[Path, int]:
    """Copy the fixture with its 5th FLASER line broken; return the file and that line number."""
    lines = FIRST20.read_text().splitlines()
    flaser = [i for i, ln in enumerate(lines) if ln.startswith("FLASER")]
    i = flaser[4]
    tokens = lines[i].split()
    if kind == "truncated":
        tokens = tokens[:100]
    elif kind == "non_numeric":
        tokens[50] = "1.2.3"
    elif kind == "wrong_count":
        tokens[1] = "181"
    elif kind == "bad_count":
        tokens[1] = "many"
    elif kind == "nan":
        tokens[10] = "nan"
    lines[i] = " ".join(tokens)
    path = tmp_path / f"{kind}.log"
    path.write_text("\n".join(lines) + "\n")
    return path, i + 1


@pytest.mark.parametrize("kind", ["truncated", "non_numeric", "wrong_count", "bad_count", "nan"])
def test_carmen_malformed_line(tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture) -> None:
    path, line_no = _malformed(tmp_path, kind)
    scans = load_scans(path)  # the header is fine: no error at the call
    with pytest.raises(OctolgpError, match=rf"{kind}\.log:{line_no}:"):
        list(scans)
    reader = load_scans(path, skip_bad=True)
    assert isinstance(reader, CarmenReader)
    with caplog.at_level(logging.INFO, logger="octolgp"):
        assert len(list(reader)) == 19
    assert reader.skipped == 1
    assert reader.bad_lines == [line_no]
    (record,) = [r for r in caplog.records if r.name == "octolgp.io.carmen"]
    assert record.levelno == logging.INFO
    assert f"{path}:{line_no}: skipped" in record.getMessage()


def test_carmen_corrupt_gzip_tail_raises_while_iterating(tmp_path: Path) -> None:
    blob = gzip.compress(FIRST20.read_bytes())
    path = tmp_path / "cut.log.gz"
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(OctolgpError, match=r"cut\.log\.gz"):
        list(load_scans(path))


def test_fr079_uses_param_max_range(shared_data: Callable[..., Path]) -> None:
    reader = load_scans(shared_data("fr079", "freiburg-079-corrected.log.gz"))
    assert isinstance(reader, CarmenReader)
    n_scans = n_no_return = 0
    for scan in reader:
        assert len(scan) == 360
        n_scans += 1
        n_no_return += _no_returns(scan)
    assert n_scans == 4791
    assert reader.no_return == pytest.approx(80.99)  # PARAM robot_front_laser_max
    assert n_no_return == 36_004


FIXTURES = Path(__file__).parent / "data"


@pytest.mark.parametrize(
    ("path", "fmt", "dim"),
    [
        ("intel_first20.log", "carmen", 2),
        ("3dtk", "3dtk", 3),
        ("rosbag/intel.bag", "rosbag", 2),
        ("rosbag/intel_ros2", "rosbag", 2),
        ("rosbag/cloud_ros2", "rosbag", 3),
        ("pointcloud/cloud_ascii.pcd", "pcd", 3),
        ("pointcloud/cloud_binary.pcd", "pcd", 3),
        ("pointcloud/cloud_compressed.pcd", "pcd", 3),
        ("pointcloud/cloud_ascii.ply", "ply", 3),
        ("pointcloud/cloud_binary.ply", "ply", 3),
        ("pointcloud/scan_small.dat", "scandat", 3),
        ("pointcloud/scan_nodes.dat", "scandat", 3),
        ("pointcloud/two_scans.graph", "graph", 3),
    ],
)
def test_load_scans_guesses_every_format(path: str, fmt: str, dim: int) -> None:
    p = FIXTURES / path
    assert detect_format(p) == fmt
    guessed = list(load_scans(p))
    named = list(load_scans(p, format=fmt))
    assert guessed
    assert all(s.dim == dim for s in guessed)
    assert len(guessed) == len(named)
    for a, b in zip(guessed, named, strict=True):
        assert np.array_equal(a.points, b.points)
        assert np.array_equal(a.origin, b.origin)


def test_the_same_cloud_reads_the_same_in_every_point_cloud_format() -> None:
    clouds = [
        next(iter(load_scans(FIXTURES / "pointcloud" / name)))
        for name in ("cloud_ascii.pcd", "cloud_binary.pcd", "cloud_compressed.pcd")
    ]
    for c in clouds[1:]:
        assert np.array_equal(c.points, clouds[0].points)
        assert np.array_equal(c.origin, clouds[0].origin)


@pytest.mark.parametrize(
    "name", ["cloud_binary.pcd", "cloud_binary.ply", "two_scans.graph", "scan_small.dat"]
)
def test_a_cut_point_cloud_file_raises_naming_the_file(tmp_path: Path, name: str) -> None:
    data = (FIXTURES / "pointcloud" / name).read_bytes()
    cut = tmp_path / name
    cut.write_bytes(data[: len(data) * 2 // 3 + 1] + (b"x 1\n" if name.endswith(".dat") else b""))
    with pytest.raises(OctolgpError, match=name.replace(".", r"\.")):
        list(load_scans(cut))
