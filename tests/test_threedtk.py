"""3DTK reader: the real example scans (cut down), frame conversion, poses, malformed input."""

from __future__ import annotations

import bz2
import gzip
import lzma
import math
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.rotations import euler_xyz_to_matrix
from octolgp.io import detect_format, load_scans, read_3dtk
from octolgp.io import threedtk as threedtk_module
from octolgp.io.threedtk import MIN_RANGE, NO_RETURN_RANGE, ThreeDTKReader
from octolgp.io.threedtk_pose import LH_TO_RH, read_frames, read_pose
from octolgp.scan import Scan

FIXTURE = Path(__file__).resolve().parent / "data" / "3dtk"


def _raw(path: Path) -> np.ndarray:
    """The points of a fixture file as written: scanner frame, left-handed, cm."""
    return np.loadtxt(lzma.open(path, "rt"))


def _raw_frame(path: Path) -> np.ndarray:
    """The last .frames matrix as written: column-major, left-handed, cm."""
    return np.loadtxt(path, ndmin=2)[-1, :16].reshape(4, 4, order="F")


def _valid(scan: Scan) -> np.ndarray:
    assert scan.max_range is not None
    return scan.points[np.linalg.norm(scan.points - scan.origin, axis=1) < scan.max_range]


def _median_nn(query: np.ndarray, reference: np.ndarray) -> float:
    d, _ = cKDTree(reference).query(query, distance_upper_bound=1.0)
    return float(np.median(d[np.isfinite(d)]))


@pytest.fixture(scope="module")
def scans() -> list[Scan]:
    return list(read_3dtk(FIXTURE))


def _write_scan(folder: Path, lines: list[str], name: str = "scan000.3d") -> Path:
    folder.mkdir(exist_ok=True)
    path = folder / name
    data = "".join(lines).encode()
    opener = {".xz": lzma.open, ".gz": gzip.open, ".bz2": bz2.open}.get(path.suffix)
    if opener is None:
        path.write_bytes(data)
    else:
        with opener(path, "wb") as fh:
            fh.write(data)
    stem = name.split(".")[0]
    (folder / f"{stem}.pose").write_text("0 0 0\n0 0 0\n")
    shutil.copyfile(FIXTURE / "scan001.frames", folder / f"{stem}.frames")
    return path


# --------------------------------------------------------------------------- the fixture


def test_counts_units_and_ranges(scans: list[Scan]) -> None:
    assert len(scans) == 3
    for n, scan in enumerate(scans):
        raw = _raw(FIXTURE / f"scan{n:03d}.3d.xz")
        r_cm = np.linalg.norm(raw, axis=1)
        assert len(scan) == np.count_nonzero(r_cm >= 100 * MIN_RANGE)  # near field dropped
        assert scan.dim == 3
        assert scan.max_range == NO_RETURN_RANGE
        assert scan.stamp is None
        r = np.linalg.norm(scan.points - scan.origin, axis=1)
        np.testing.assert_allclose(np.sort(r), np.sort(r_cm[r_cm >= 20]) / 100, rtol=1e-12)
        no_return = r >= NO_RETURN_RANGE
        assert no_return.any()  # the no-returns, written at 32.76-32.77 m
        assert np.all((r[no_return] > 32.75) & (r[no_return] < 32.77))
        assert r[~no_return].max() < 32.4


def test_points_follow_3dtk_convention(scans: list[Scan]) -> None:
    # Oracle: 3DTK's p_world = R p + t (left-handed, cm), then C p / 100.
    for n, scan in enumerate(scans):
        raw = _raw(FIXTURE / f"scan{n:03d}.3d.xz")
        raw = raw[np.linalg.norm(raw, axis=1) >= 20]
        T = _raw_frame(FIXTURE / f"scan{n:03d}.frames")
        expected = (raw @ T[:3, :3].T + T[:3, 3]) @ LH_TO_RH.T / 100
        # up to the re-orthonormalised rotation: 0.02 mm at most
        np.testing.assert_allclose(scan.points, expected, rtol=0, atol=2e-5)
        np.testing.assert_allclose(scan.origin, LH_TO_RH @ T[:3, 3] / 100, atol=1e-15)
    assert np.linalg.det(LH_TO_RH) == pytest.approx(-1.0)


def test_right_handed_metric_world_frame(scans: list[Scan]) -> None:
    # Data README: sensors 1.568 m and 3.378 m forward (+x), the hall on the left (+y),
    # the floor at z = -0.40 to -0.45 m and the ceiling at 2.0 m near the start.
    np.testing.assert_allclose(scans[1].origin, [1.568, 0.036, -0.091], atol=1e-3)
    np.testing.assert_allclose(scans[2].origin, [3.378, 0.081, -0.157], atol=1e-3)
    valid = np.vstack([_valid(s) for s in scans])
    np.testing.assert_allclose(valid.min(0)[:2], [0.00, -1.19], atol=0.01)
    np.testing.assert_allclose(valid.max(0)[:2], [34.53, 12.55], atol=0.01)
    p = _valid(scans[0])
    corridor = p[(np.abs(p[:, 1]) < 0.5) & (p[:, 0] > 0.5) & (p[:, 0] < 2.0)]
    floor, ceiling = np.percentile(corridor[:, 2], [2, 98])
    assert -0.55 < floor < -0.35
    assert 1.95 < ceiling < 2.15


def test_pose_files() -> None:
    # scan000 is the identity in both files.
    np.testing.assert_array_equal(read_pose(FIXTURE / "scan000.pose"), np.eye(4))
    np.testing.assert_array_equal(read_frames(FIXTURE / "scan000.frames")[-1], np.eye(4))
    # scan002's first ICP step is its .pose: this pins R = Rx Ry Rz, degrees, column-major.
    np.testing.assert_allclose(
        read_pose(FIXTURE / "scan002.pose"), read_frames(FIXTURE / "scan002.frames")[0], atol=1e-6
    )
    # The final registration moved scan001 and scan002 by under 1 degree and 2 cm.
    for n in (1, 2):
        T_pose = read_pose(FIXTURE / f"scan{n:03d}.pose")
        T_frames = read_frames(FIXTURE / f"scan{n:03d}.frames")[-1]
        cos = (np.trace(T_pose[:3, :3].T @ T_frames[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(min(cos, 1.0))) < 1.0
        assert np.linalg.norm(T_pose[:3, 3] - T_frames[:3, 3]) < 0.02
    assert read_frames(FIXTURE / "scan001.frames").shape == (3, 4, 4)


def test_origin_is_the_pose_translation() -> None:
    for kind in ("pose", "frames"):
        reader = read_3dtk(FIXTURE, pose=kind)
        for n, scan in enumerate(reader):
            path = FIXTURE / f"scan{n:03d}.{kind}"
            T = read_pose(path) if kind == "pose" else read_frames(path)[-1]
            np.testing.assert_array_equal(reader.transforms[n], T)
            np.testing.assert_array_equal(scan.origin, T[:3, 3])
    t_cm = np.loadtxt(FIXTURE / "scan001.pose")[0]
    first = next(read_3dtk(FIXTURE, pose="pose", first=1))
    np.testing.assert_allclose(first.origin, np.array([t_cm[2], -t_cm[0], t_cm[1]]) / 100)


def test_euler_matrix_is_3dtk_euler_to_matrix4() -> None:
    # 3DTK globals.icc EulerToMatrix4, written out, column-major.
    theta = np.radians([1.35694, -0.852409, -0.56224])
    sx, sy, sz = np.sin(theta)
    cx, cy, cz = np.cos(theta)
    m = [cy * cz, sx * sy * cz + cx * sz, -cx * sy * cz + sx * sz]
    m += [-cy * sz, -sx * sy * sz + cx * cz, cx * sy * sz + sx * cz]
    m += [sy, -sx * cy, cx * cy]
    expected = np.reshape(m, (3, 3), order="F")
    np.testing.assert_allclose(
        euler_xyz_to_matrix(np.degrees(theta), degrees=True), expected, atol=1e-15
    )


def test_registered_scans_overlap(scans: list[Scan]) -> None:
    reference = _valid(scans[0])
    registered = _valid(scans[1])
    T = read_frames(FIXTURE / "scan001.frames")[-1]
    local = (registered - T[:3, 3]) @ T[:3, :3]  # back to the scanner frame
    transposed = local @ T[:3, :3] + T[:3, 3]
    by_pose = _valid(next(read_3dtk(FIXTURE, pose="pose", first=1, last=1)))
    assert _median_nn(registered, reference) < 0.030  # 2.8 cm
    assert _median_nn(by_pose, reference) < 0.035  # 3.1 cm
    assert _median_nn(transposed, reference) > _median_nn(registered, reference) + 0.004
    assert _median_nn(local, reference) > 0.15  # unregistered: 23 cm


def test_first_last_and_single_file() -> None:
    assert len(read_3dtk(FIXTURE, first=1).files) == 2
    assert [f.name for f in read_3dtk(FIXTURE, last=0).files] == ["scan000.3d.xz"]
    assert [f.name for f in read_3dtk(FIXTURE, first=1, last=1).files] == ["scan001.3d.xz"]
    single = list(read_3dtk(FIXTURE / "scan001.3d.xz"))
    assert len(single) == 1
    np.testing.assert_array_equal(single[0].points, next(read_3dtk(FIXTURE, first=1)).points)
    with pytest.raises(OctolgpError, match=r"numbered 5\.\.None"):
        read_3dtk(FIXTURE, first=5)
    with pytest.raises(OctolgpError, match="not in"):
        read_3dtk(FIXTURE / "scan001.3d.xz", last=0)


def test_load_scans_detects_3dtk(scans: list[Scan]) -> None:
    assert detect_format(FIXTURE) == "3dtk"
    assert detect_format(FIXTURE / "scan000.3d.xz") == "3dtk"
    reader = load_scans(FIXTURE, skip_bad=True)
    assert isinstance(reader, ThreeDTKReader)
    assert reader.skip_bad
    loaded = list(reader)
    assert len(loaded) == len(scans)
    for a, b in zip(loaded, scans, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
    assert next(load_scans(FIXTURE / "scan002.3d.xz", format="3dtk")).points.shape[1] == 3


def test_max_and_min_range_options(scans: list[Scan]) -> None:
    raw = _raw(FIXTURE / "scan000.3d.xz")
    every = next(read_3dtk(FIXTURE, last=0, min_range=0.0, max_range=math.inf))
    assert len(every) == len(raw)
    assert every.max_range is None
    reader = read_3dtk(FIXTURE, last=0, max_range=10.0)
    assert next(reader).max_range == 10.0
    assert reader.near_field == np.count_nonzero(np.linalg.norm(raw, axis=1) < 20)
    for bad in ({"min_range": -1.0}, {"max_range": 0.1}, {"pose": "euler"}, {"first": 1.5}):
        with pytest.raises(OctolgpError):
            read_3dtk(FIXTURE, **bad)


# --------------------------------------------------------------------------- errors


def test_missing_paths(tmp_path: Path) -> None:
    with pytest.raises(MapFileNotFound):
        read_3dtk(tmp_path / "nope")
    with pytest.raises(MapFileNotFound):
        load_scans(tmp_path / "nope.3d.xz")
    shutil.copyfile(FIXTURE / "scan001.3d.xz", tmp_path / "scan001.3d.xz")
    shutil.copyfile(FIXTURE / "scan001.pose", tmp_path / "scan001.pose")
    with pytest.raises(MapFileNotFound, match=r"scan001\.frames"):
        read_3dtk(tmp_path)
    assert len(list(read_3dtk(tmp_path, pose="pose"))) == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(OctolgpError, match=r"no scanNNN\.3d files"):
        read_3dtk(empty)


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ("1 2\n", "got 2 fields"),
        ("1 2 3 4\n", "got 4 fields"),
        ("1 2 x\n", "non-numeric"),
        ("1 nan 3\n", "NaN or inf"),
        ("1 2 inf\n", "NaN or inf"),
    ],
)
def test_malformed_point_line(tmp_path: Path, bad: str, why: str) -> None:
    lines = ["100 0 0\n"] * 9 + [bad] + ["0 100 0\n"] * 5
    path = _write_scan(tmp_path / "d", lines)
    with pytest.raises(OctolgpError, match=rf"{path}:10: .*{why}"):
        list(read_3dtk(path.parent))
    reader = read_3dtk(path.parent, skip_bad=True)
    (scan,) = list(reader)
    assert len(scan) == 14
    assert reader.skipped == 1
    assert reader.bad_lines == [(path, 10)]


@pytest.mark.parametrize("suffix", ["", ".xz", ".gz", ".bz2"])
def test_compression_and_legacy_header(tmp_path: Path, suffix: str) -> None:
    lines = ["360 x 225\n", "100 0 0\n", "\n", "0 0 100\n", "0 200 0\n"]
    path = _write_scan(tmp_path, lines, f"scan007.3d{suffix}")
    assert detect_format(path) == detect_format(tmp_path) == "3dtk"
    (scan,) = list(read_3dtk(tmp_path))
    T = read_frames(tmp_path / "scan007.frames")[-1]
    local = (scan.points - T[:3, 3]) @ T[:3, :3]  # x right, z forward, y up -> -y, x, z
    np.testing.assert_allclose(local, [[0, -1, 0], [1, 0, 0], [0, 0, 2]], atol=1e-12)
    path = _write_scan(tmp_path, ["100 2 3\n", "7\n"], f"scan007.3d{suffix}")
    with pytest.raises(OctolgpError, match=rf"{path}:2: expected 3 numbers 'x y z', got 1 fields"):
        list(read_3dtk(tmp_path))


def test_corrupt_stream_and_empty_scan(tmp_path: Path) -> None:
    path = _write_scan(tmp_path, ["100 0 0\n"] * 1000, "scan000.3d.xz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(OctolgpError, match=rf"{path}:\d+: unreadable"):
        list(read_3dtk(tmp_path))
    _write_scan(tmp_path, ["1 0 0\n"], "scan000.3d.xz")
    with pytest.raises(OctolgpError, match="no point at or beyond"):
        list(read_3dtk(tmp_path))
    _write_scan(tmp_path, ["\n", "a b c\n"], "scan000.3d.xz")
    with pytest.raises(OctolgpError, match=r"scan000\.3d\.xz: no points"):
        list(read_3dtk(tmp_path, skip_bad=True))


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("pose", "0 0 0\n0 0\n", ":2: expected 3 numbers"),
        ("pose", "0 0 0\n", "expected 2 lines"),
        ("pose", "0 0 0\n\n0 x 0\n", ":3: could not convert"),
        ("frames", "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n1 0 0\n", ":2: expected 17 numbers"),
        ("frames", "2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n", ":1: not a rigid transform"),
        ("frames", "-1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n", ":1: not a rigid transform"),
        ("frames", "1 0 0 0 0 1 0 0 0 0 1 0 0 0 nan 1 2\n", ":1: NaN or inf"),
        ("frames", "\n", "is empty"),
    ],
)
def test_malformed_pose_files(tmp_path: Path, name: str, text: str, where: str) -> None:
    _write_scan(tmp_path, ["100 0 0\n"])
    (tmp_path / f"scan000.{name}").write_text(text)
    with pytest.raises(OctolgpError, match=rf"scan000\.{name}{where}|{where}"):
        read_3dtk(tmp_path, pose=name)


def test_duplicate_scan_numbers(tmp_path: Path) -> None:
    _write_scan(tmp_path, ["100 0 0\n"], "scan000.3d")
    _write_scan(tmp_path, ["100 0 0\n"], "scan000.3d.gz")
    with pytest.raises(OctolgpError, match="are scan 0"):
        read_3dtk(tmp_path)


@given(
    n=st.integers(1, 400),
    bad=st.sets(st.integers(0, 399), max_size=12),
    chunk=st.sampled_from([64, 1000, 1 << 22]),
)
def test_skip_bad_finds_every_malformed_line(n: int, bad: set[int], chunk: int) -> None:
    # Bisection over chunks must name exactly the bad lines and keep every good one in order.
    bad = {i for i in bad if i < n}
    good = [i for i in range(n) if i not in bad]
    if not good:
        return
    lines = [f"{i + 100} 0.5 -{i}\n" if i not in bad else f"{i} oops\n" for i in range(n)]
    with tempfile.TemporaryDirectory() as tmp:
        path = _write_scan(Path(tmp), lines)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(threedtk_module, "_CHUNK_BYTES", chunk)
            reader = read_3dtk(path, skip_bad=True, pose="pose", min_range=0.0)
            (scan,) = list(reader)
            assert reader.bad_lines == [(path, i + 1) for i in sorted(bad)]
            expected = np.array([[i + 100, 0.5, -i] for i in good]) @ LH_TO_RH.T / 100
            np.testing.assert_allclose(scan.points, expected, atol=1e-12)
            if bad:
                with pytest.raises(OctolgpError, match=rf":{min(bad) + 1}: .* got 2 fields"):
                    list(read_3dtk(path, pose="pose"))


# --------------------------------------------------------------------------- full data


def test_full_example_scans_match_the_data_readme(shared_data: Callable[..., Path]) -> None:
    scans = list(read_3dtk(shared_data("3dtk_example_scans")))
    no_returns, valid = [], []
    for scan in scans:
        r = np.linalg.norm(scan.points - scan.origin, axis=1)
        no_returns.append(int((r >= NO_RETURN_RANGE).sum()))
        valid.append(int((r < NO_RETURN_RANGE).sum()))
    assert no_returns == [1481, 1313, 1618]
    assert valid == [77987, 78320, 78118]
    nn = [_median_nn(_valid(scans[i + 1]), _valid(scans[i])) for i in (0, 1)]
    np.testing.assert_allclose(nn, [0.0289, 0.0314], atol=5e-4)
