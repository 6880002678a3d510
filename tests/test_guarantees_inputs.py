"""Inputs never lose or invent data: scans own their arrays, readers refuse what they cannot trust.

Each test is one way an input could silently change a map: a scan that aliases the
caller's buffer, a recording replayed from its lossy display copy, flipped bytes in a
recording, and files whose headers claim more data than any scan holds (decompression
bombs), which must be refused from the header before anything is read or inflated.
"""

from __future__ import annotations

import array
import gzip
import logging
import math
import re
import struct
import subprocess
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rerun as rr

from octolgp import (
    Hyperparameters,
    LatticeConfig,
    MapConfig,
    OctolgpError,
    OnlineConfig,
    OnlineMap,
    Scan,
    TrainingConfig,
    load_scans,
)
from octolgp.io import limits, npz, pcd
from octolgp.io.carmen import CarmenReader
from octolgp.io.octomap_graph import ScanDatReader
from octolgp.io.pcd import PcdReader
from octolgp.io.ply import PlyReader
from octolgp.io.rrd_read import read_rrd
from octolgp.io.rrd_write import log_scan
from octolgp.io.threedtk import ThreeDTKReader
from octolgp.sinks.rerun import RerunSink, open_recording

# --- Scan owns copies of its arrays ------------------------------------------------


def _wall(n: int = 50) -> np.ndarray:
    """``n`` endpoints on the wall x = 3, as a fresh writeable C-contiguous float64 array."""
    return np.c_[np.full(n, 3.0), np.linspace(-1.0, 1.0, n)]


def test_scan_copies_the_callers_arrays_and_leaves_them_writeable() -> None:
    origin = np.array([0.5, -0.25])
    points = _wall()
    want_o, want_p = origin.copy(), points.copy()
    scan = Scan(origin=origin, points=points, max_range=10.0)
    assert origin.flags.writeable
    assert points.flags.writeable
    assert not np.shares_memory(scan.points, points)
    assert not np.shares_memory(scan.origin, origin)
    points[:] = 99.0
    origin[:] = -7.0
    np.testing.assert_array_equal(scan.points, want_p)
    np.testing.assert_array_equal(scan.origin, want_o)
    assert not scan.points.flags.writeable
    assert not scan.origin.flags.writeable


def test_a_reused_buffer_does_not_change_the_scans_already_made() -> None:
    """A robot loop that refills one buffer for every scan keeps every scan it made."""
    buf = np.empty((40, 3))
    pose = np.empty(3)
    scans = []
    for k in range(4):
        buf[:] = k + np.arange(120, dtype=float).reshape(40, 3) / 100.0
        pose[:] = (k, 0.0, 1.0)
        scans.append(Scan(pose, buf, stamp=float(k)))
    for k, scan in enumerate(scans):
        assert scan.points[0, 0] == pytest.approx(k)
        assert scan.origin[0] == k


def test_views_and_buffers_are_copied() -> None:
    """A slice of a larger array, a transposed view and an ``array.array`` are copied too."""
    big = np.arange(200, dtype=float).reshape(100, 2)
    view = big[10:20]
    col_major = np.asfortranarray(big[:5])
    raw = array.array("d", [1.0, 2.0])
    s1 = Scan(raw, view)
    s2 = Scan(big[0], col_major)
    before = (s1.points.copy(), s1.origin.copy(), s2.points.copy(), s2.origin.copy())
    big[:] = -1.0
    col_major[:] = -1.0
    raw[0] = -1.0
    for got, want in zip((s1.points, s1.origin, s2.points, s2.origin), before, strict=True):
        np.testing.assert_array_equal(got, want)
    assert big.flags.writeable
    assert view.flags.writeable
    assert col_major.flags.writeable


def test_constructors_keep_no_reference_to_their_inputs() -> None:
    """from_ranges, from_laserscan, from_pointcloud2 and downsample give scans of their own."""
    ranges = np.array([1.0, 2.0, 3.0, 30.0])
    angles = np.array([0.0, 0.5, 1.0, 1.5])
    pose = np.array([1.0, 2.0, 0.0])
    s = Scan.from_ranges(pose, ranges, angles, max_range=25.0)
    want = s.points.copy()
    ranges[:] = 0.5
    angles[:] = 0.0
    pose[:] = 0.0
    np.testing.assert_array_equal(s.points, want)
    assert ranges.flags.writeable
    assert pose.flags.writeable

    laser = SimpleNamespace(
        angle_min=0.0,
        angle_increment=0.25,
        range_min=0.1,
        range_max=20.0,
        ranges=array.array("f", [1.0, 2.0, 4.0]),
    )
    s = Scan.from_laserscan(laser, (0.0, 0.0, 0.0))
    want = s.points.copy()
    laser.ranges[0] = 9.0
    np.testing.assert_array_equal(s.points, want)

    xyz = np.array([[1.0, 0.0, 0.5], [0.0, 2.0, 0.5], [3.0, 3.0, 0.5]])
    data = np.ascontiguousarray(xyz).view(np.uint8).reshape(-1).copy()
    cloud = SimpleNamespace(
        height=1,
        width=3,
        fields=[
            SimpleNamespace(name=c, offset=8 * i, datatype=8, count=1) for i, c in enumerate("xyz")
        ],
        is_bigendian=False,
        point_step=24,
        row_step=72,
        data=data,
    )
    s = Scan.from_pointcloud2(cloud, np.eye(4))
    np.testing.assert_array_equal(s.points, xyz)
    data[:] = 0
    np.testing.assert_array_equal(s.points, xyz)
    assert data.flags.writeable

    full = Scan(np.zeros(2), _wall(200), max_range=50.0, stamp=1.5)
    d = full.downsample(0.1)
    assert not np.shares_memory(d.points, full.points)
    assert not np.shares_memory(d.origin, full.origin)
    assert (d.max_range, d.stamp) == (50.0, 1.5)
    assert not d.points.flags.writeable
    assert 0 < len(d) < 200


# --- Rerun replay: the exact copy or nothing ----------------------------------------

MAX_RANGE = 81.82  # the Intel lab log's no-return threshold, a hair below 81.83 m
HP = Hyperparameters(length_scale=0.4, signal_variance=1.0, noise_variance=0.05, alpha=6.0)


def _room_scan(k: int) -> Scan:
    """A 2D scan in a 6 m room whose every third beam is a no-return (81.83 m long)."""
    ang = np.linspace(-np.pi, np.pi, 60, endpoint=False) + 0.01 * k
    r = np.full(60, 3.0 + 0.1 * k)
    r[::3] = 81.83
    o = np.array([0.1 * k, -0.05 * k])
    return Scan(o, o + r[:, None] * np.c_[np.cos(ang), np.sin(ang)], max_range=MAX_RANGE)


SINK_SCANS = [_room_scan(k) for k in range(6)]


@pytest.fixture(scope="module")
def sink_recording(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """SINK_SCANS mapped online and streamed to a file by the sink (one flush per scan)."""
    path = tmp_path_factory.mktemp("sink") / "full.rrd"
    rec, _ = open_recording(save=path)
    # whole no-returns and every voxel filled: a recording whose chunks put the first
    # scan's display copy before its exact copy, the case the cuts below need
    config = MapConfig(
        dim=2,
        resolution=0.2,
        hyperparameters=HP,
        training=TrainingConfig(no_return_range=math.inf),
        lattice=LatticeConfig(fill_voxels=-1),
    )
    with OnlineMap(config, sink=RerunSink(rec)) as m:
        for scan in SINK_SCANS:
            m.insert_scan(scan)
            rec.flush()
    rec.disconnect()
    return path.read_bytes()


def _messages(data: bytes) -> list[tuple[int, int]]:
    """``(start, end)`` of the data messages of a one-stream RRD file (before its End)."""
    out, off = [], 12
    while off + 16 <= len(data):
        kind, length = struct.unpack_from("<QQ", data, off)
        if kind == 0:
            break
        out.append((off, off + 16 + length))
        off += 16 + length
    return out


def _replay(path: Path) -> tuple[list[Scan], str | None]:
    """The scans replayed from ``path``, or the message of the OctolgpError it raised."""
    try:
        return list(read_rrd(path)), None
    except OctolgpError as exc:
        return [], str(exc)


def _same(got: Scan, want: Scan, *, kept: bool = False) -> None:
    """``got`` is ``want``; ``kept``: as a map kept it (rounded to ``OnlineConfig.scan_precision``)."""
    precision = OnlineConfig().scan_precision
    assert precision is not None
    np.testing.assert_array_equal(
        got.points, want.rounded(precision).points if kept else want.points
    )
    np.testing.assert_array_equal(got.origin, want.origin)
    assert got.max_range == want.max_range


def test_a_cut_recording_never_replays_no_returns_as_hits(
    tmp_path: Path, sink_recording: bytes
) -> None:
    """Cut inside a message: the replay is exact scans, or an error; never the display copy.

    The cuts fall in each of the first scan's messages and around each scan copy.
    """
    data = sink_recording
    messages = _messages(data)
    exact = [i for i, (a, b) in enumerate(messages) if b"/octolgp/scan" in data[a:b]]
    shown = [i for i, (a, b) in enumerate(messages) if b"/world/sensor/points" in data[a:b]]
    assert len(exact) == len(shown) == len(SINK_SCANS)
    first = max(exact[0], shown[0]) + 2
    where = sorted({*range(first), *(j + d for j in exact + shown for d in (0, 1))})
    refused = 0
    for i in where:
        start = messages[min(i, len(messages) - 1)][0]
        cut = tmp_path / f"cut{i}.rrd"
        cut.write_bytes(data[: start + 40])  # inside message i
        got, error = _replay(cut)
        if error is not None:
            assert str(cut) in error
            if "exact copies" in error:
                refused += 1
                assert any(j < i for j in shown)  # refused only where a display copy was read
            continue
        assert got, cut
        for scan, want in zip(got, SINK_SCANS, strict=False):
            _same(scan, want, kept=True)  # a prefix of the exact scans: max_range kept
    # The sink writes a scan's display copy before its exact copy at least once (the first
    # scan), so some cuts hold a display copy and no exact one.
    assert min(shown) < min(exact)
    assert refused >= 1
    # Named explicitly, with a max_range, the display copy can still be replayed.
    i = next(i for i in range(len(messages)) if min(shown) < i <= min(exact))
    cut = tmp_path / f"cut{i}.rrd"
    got = list(read_rrd(cut, points="world/sensor/points", max_range=MAX_RANGE))
    assert got
    assert all(s.max_range == MAX_RANGE for s in got)


def test_scans_whose_exact_copy_is_lost_are_left_out_with_one_warning(
    tmp_path: Path, sink_recording: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    """Display copies of six scans, exact copies of four: replay four, warn once naming two."""
    data = sink_recording
    messages = _messages(data)
    exact = [(a, b) for a, b in messages if b"/octolgp/scan" in data[a:b]]
    dropped = set(exact[4:])
    damaged = tmp_path / "damaged.rrd"
    damaged.write_bytes(
        data[:12] + b"".join(data[a:b] for a, b in messages if (a, b) not in dropped)
    )
    with caplog.at_level(logging.WARNING, logger="octolgp"):
        reader = read_rrd(damaged)
        got = list(reader)
    assert len(got) == 4
    for scan, want in zip(got, SINK_SCANS, strict=False):
        _same(scan, want, kept=True)
    assert reader.lost == 2
    lost = [r.getMessage() for r in caplog.records if "display copy" in r.getMessage()]
    assert len(lost) == 1, lost
    assert "2 of 6 scans" in lost[0]
    assert str(damaged) in lost[0]


def _old_log_scan(rec: rr.RecordingStream, scan: Scan, index: int) -> None:
    """What log_scan wrote before exact copies had a checksum and display rows a mark."""
    rec.set_time("scan", sequence=index)
    rec.log("world/sensor", rr.Transform3D(translation=[*scan.origin, 0.0], mat3x3=np.eye(3)))
    rec.log("world/sensor/points", rr.Points2D(scan.points - scan.origin))
    components = {
        "origin": scan.origin,
        "points": scan.points.reshape(-1),
        "dim": np.array([scan.dim], dtype=np.int64),
        "max_range": np.array([scan.max_range]),
        "stamp": np.array([np.nan]),
    }
    rec.log("octolgp/scan", rr.DynamicArchetype("octolgp.Scan", components=components))
    rec.log("metrics/insert_seconds", rr.Scalars(0.1))
    rec.flush()


def test_old_recordings_read_unchecked_and_are_refused_without_exact_copies(
    tmp_path: Path,
) -> None:
    old = tmp_path / "old.rrd"
    rec = rr.RecordingStream("octolgp")
    rec.save(old)
    for k, scan in enumerate(SINK_SCANS[:3]):
        _old_log_scan(rec, scan, k)
    rec.disconnect()
    got = list(read_rrd(old))
    assert len(got) == 3
    for scan, want in zip(got, SINK_SCANS, strict=False):
        _same(scan, want)
    # The same recording without any exact copy: the sink's metrics give it away.
    data = old.read_bytes()
    messages = _messages(data)
    stripped = tmp_path / "stripped.rrd"
    stripped.write_bytes(
        data[:12] + b"".join(data[a:b] for a, b in messages if b"/octolgp/scan" not in data[a:b])
    )
    with pytest.raises(OctolgpError, match=re.escape(str(stripped)) + ".*exact copies"):
        read_rrd(stripped)


def _flip_mantissas(data: bytearray, at: int, count: int = 8) -> None:
    """Flip the 52 mantissa bits of ``count`` float64 at ``at``: values change, stay finite."""
    values = np.frombuffer(bytes(data[at : at + 8 * count]), dtype="<u8") ^ np.uint64(2**52 - 1)
    data[at : at + 8 * count] = values.tobytes()


@pytest.mark.parametrize("part", ["points", "origin"])
def test_flipped_bytes_in_an_exact_copy_raise_naming_the_scan(tmp_path: Path, part: str) -> None:
    rng = np.random.default_rng(7)
    scans = [Scan(rng.normal(size=3), rng.normal(size=(300, 3)) * 5.0) for _ in range(4)]
    path = tmp_path / "run.rrd"
    rec = rr.RecordingStream("octolgp_test")
    rec.save(path)
    for k, scan in enumerate(scans):
        log_scan(rec, scan, k)
        rec.flush()
    rec.disconnect()
    for a, b in zip(read_rrd(path), scans, strict=True):
        _same(a, b)
    data = bytearray(path.read_bytes())
    payload = getattr(scans[2], part).tobytes()
    at = data.find(payload[:24])
    assert at > 0
    assert data.find(payload[:24], at + 1) < 0
    _flip_mantissas(data, at, count=8 if part == "points" else 3)
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(bytes(data))
    with pytest.raises(OctolgpError, match=re.escape(str(bad)) + r".*scan=2.*corrupt"):
        list(read_rrd(bad))
    # skip_bad leaves the corrupt scan out: it is never replaced by its display copy.
    reader = read_rrd(bad, skip_bad=True)
    got = list(reader)
    assert len(got) == 3
    for a, b in zip(got, [scans[0], scans[1], scans[3]], strict=True):
        _same(a, b)
    assert reader.skipped == 1


# --- Size limits, checked from headers before reading or decompressing ---------------

ROOT = Path(__file__).resolve().parents[1]
HUGE = 10**12

RSS_PROBE = """
import sys
from octolgp.errors import OctolgpError
from octolgp.io import load_scans
from octolgp.memory import peak_rss_mb, reset_peak_rss, rss_mb
before = rss_mb()
assert reset_peak_rss()  # the peak since now (ru_maxrss would start at pytest's RSS)
try:
    list(load_scans(sys.argv[1]))
    print("read")
except OctolgpError as exc:
    print("OctolgpError:", exc)
grown = round((peak_rss_mb() - before) * 1e3)
print("grown_kib", grown)
"""


def _probe(path: Path) -> tuple[str, int]:
    """Read ``path`` in a fresh interpreter: its first output line and its RSS growth (KiB)."""
    out = subprocess.run(
        [sys.executable, "-c", RSS_PROBE, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        check=True,
    ).stdout.splitlines()
    return out[0], int(out[-1].split()[1])


def _lzf_zeros(nbytes: int) -> bytes:
    """An LZF stream of ``nbytes`` zero bytes at LZF's largest ratio (264 bytes per 3)."""
    out = bytearray(b"\x00\x00")  # a literal run of one byte, 0
    full, rest = divmod(nbytes - 1, 264)
    out += b"\xe0\xff\x00" * full  # back-reference: length 7 + 255 + 2, distance 1
    while rest:
        k = min(rest, 8)
        out += bytes([k - 1]) + bytes(k) if k < 3 else bytes([(k - 2) << 5, 0])
        rest -= k
    return bytes(out)


def _pcd_head(points: int | str, data: str, fields: str = "x y z", sizes: str = "4 4 4") -> bytes:
    n = len(fields.split())
    counts = " ".join(["1"] * n)
    if fields == "x y z h":
        counts = "1 1 1 100"
    return (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {' '.join(['F'] * n)}\n"
        f"COUNT {counts}\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {points}\nDATA {data}\n"
    ).encode()


@pytest.fixture
def no_pcd_data(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make reading or decompressing any PCD data fail the test."""

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("the data were read")

    monkeypatch.setattr(pcd, "_lzf", boom)
    for name in ("_read_ascii", "_read_binary"):
        monkeypatch.setattr(PcdReader, name, boom)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
@pytest.mark.usefixtures("no_pcd_data")
def test_a_pcd_header_claiming_1e12_points_is_refused_before_reading(
    tmp_path: Path, data: str
) -> None:
    path = tmp_path / "huge.pcd"
    tail = struct.pack("<II", 16, 2**32 - 1) + bytes(16) if data == "binary_compressed" else b""
    path.write_bytes(_pcd_head(HUGE, data) + tail)
    want = rf"huge\.pcd:9: POINTS claims {HUGE} points, more than .*MAX_SCAN_POINTS"
    with pytest.raises(OctolgpError, match=want):
        list(PcdReader(path))


@pytest.mark.usefixtures("no_pcd_data")
def test_pcd_lzf_sizes_are_checked_before_decompressing(tmp_path: Path) -> None:
    path = tmp_path / "c.pcd"
    # Within MAX_SCAN_POINTS, but 3,000,000 points x 412 bytes inflate past 1 GiB.
    raw = 3_000_000 * 412
    head = _pcd_head(3_000_000, "binary_compressed", "x y z h", "4 4 4 4")
    path.write_bytes(head + struct.pack("<II", 1 << 24, raw) + bytes(64))
    with pytest.raises(OctolgpError, match=rf"c\.pcd: byte \d+: .*{raw} bytes .*MAX_DECOMPRESSED"):
        list(PcdReader(path))
    # 10 bytes of LZF cannot inflate to 12,000.
    path.write_bytes(
        _pcd_head(1000, "binary_compressed") + struct.pack("<II", 10, 12000) + bytes(10)
    )
    with pytest.raises(OctolgpError, match=r"c\.pcd: byte \d+: corrupt LZF sizes.*88-fold"):
        list(PcdReader(path))
    # A block stated larger than the file.
    path.write_bytes(_pcd_head(1000, "binary_compressed") + struct.pack("<II", 9000, 12000))
    with pytest.raises(OctolgpError, match=r"truncated LZF block: its 9000 bytes are stated, 0"):
        list(PcdReader(path))


def test_a_pcd_lzf_bomb_is_refused_with_bounded_memory(tmp_path: Path) -> None:
    """2.3 MB of LZF that inflate to 200 MB: one point more than MAX_SCAN_POINTS."""
    points = limits.MAX_SCAN_POINTS + 1
    body = _lzf_zeros(points * 12)
    path = tmp_path / "bomb.pcd"
    path.write_bytes(
        _pcd_head(points, "binary_compressed") + struct.pack("<II", len(body), points * 12) + body
    )
    assert path.stat().st_size < 3 << 20
    first, grown = _probe(path)
    assert first.startswith("OctolgpError:"), first
    assert "bomb.pcd:9: POINTS claims" in first
    assert grown < 32 << 10, f"RSS grew by {grown} KiB"


def _zip_npz(path: Path, members: dict[str, tuple[dict[str, object], bytes]]) -> None:
    """An npz archive of members given as (npy header, data bytes), deflated."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, (header, data) in members.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as m:
                np.lib.format.write_array_header_1_0(m, header)
                m.write(data)


def _npy(arr: np.ndarray) -> tuple[dict[str, object], bytes]:
    return np.lib.format.header_data_from_array_1_0(arr), arr.tobytes()


@pytest.fixture
def no_np_load(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make loading any array of an npz file fail the test."""

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("an array was loaded")

    monkeypatch.setattr(np, "load", boom)


@pytest.mark.usefixtures("no_np_load")
def test_an_npz_member_claiming_a_huge_shape_is_refused_before_loading(tmp_path: Path) -> None:
    path = tmp_path / "huge.npz"
    header = {"descr": "<f8", "fortran_order": False, "shape": (HUGE, 3)}
    _zip_npz(
        path,
        {
            "origins": _npy(np.zeros((1, 3))),
            "points": (header, bytes(48)),
            "offsets": _npy(np.array([0, 2])),
        },
    )
    want = rf"huge\.npz.*array 'points' claims shape \({HUGE}, 3\).*MAX_DECOMPRESSED_BYTES"
    with pytest.raises(OctolgpError, match=want):
        npz.read_npz(path)
    # A bare .npy (no archive) whose header claims as much is refused from its magic.
    bare = tmp_path / "bare.npz"
    with bare.open("wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
    with pytest.raises(OctolgpError, match=r"bare\.npz.*holds one array, not an npz archive"):
        npz.read_npz(bare)


def test_npz_scan_sizes_are_checked_before_the_points_are_read(tmp_path: Path) -> None:
    """Offsets giving one scan more than MAX_SCAN_POINTS: refused before ``points`` is read."""
    path = tmp_path / "big_scan.npz"
    n = limits.MAX_SCAN_POINTS + 1
    header = {"descr": "<f8", "fortran_order": False, "shape": (n, 2)}
    _zip_npz(
        path,
        {
            "offsets": _npy(np.array([0, n])),
            "origins": _npy(np.zeros((1, 2))),
            "points": (header, bytes(64)),  # truncated: reading it would fail differently
        },
    )
    with pytest.raises(OctolgpError, match=rf"'offsets' gives scan 0 {n} points, more than"):
        npz.read_npz(path)


def test_an_npz_bomb_is_refused_with_bounded_memory(tmp_path: Path) -> None:
    """1.08 GB of zeros deflated into a few MB, streamed so this test stays small."""
    n = 45_000_000
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, arr in (("origins", np.zeros((1, 3))), ("offsets", np.array([0, n]))):
            with zf.open(name + ".npy", "w") as m:
                np.lib.format.write_array(m, arr)
        with zf.open("points.npy", "w", force_zip64=True) as m:
            header = {"descr": "<f8", "fortran_order": False, "shape": (n, 3)}
            np.lib.format.write_array_header_1_0(m, header)
            zeros = bytes(1 << 22)
            for _ in range(n * 24 // len(zeros)):
                m.write(zeros)
            m.write(bytes(n * 24 % len(zeros)))
    assert path.stat().st_size < 8 << 20
    first, grown = _probe(path)
    assert first.startswith("OctolgpError:"), first
    assert "'points' claims shape (45000000, 3)" in first
    assert grown < 32 << 10, f"RSS grew by {grown} KiB"


CARMEN_LINE = "FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0\n"


def _carmen_gz(path: Path, long_line: int) -> None:
    """A gzip CARMEN log: PARAM, a scan, a ``long_line``-character FLASER line, a scan."""
    with gzip.open(path, "wb", compresslevel=6) as fh:
        fh.write(("PARAM robot_front_laser_max 81.83\n" + CARMEN_LINE).encode())
        fh.write(b"FLASER ")
        zeros = b"0" * (1 << 20)
        for _ in range(long_line // len(zeros)):
            fh.write(zeros)
        fh.write(b"0" * (long_line % len(zeros)) + b"\n" + CARMEN_LINE.encode())


def test_an_enormous_carmen_line_is_refused_with_bounded_memory(tmp_path: Path) -> None:
    """50 MB of zeros in one line, gzipped to about 50 kB."""
    path = tmp_path / "bomb.log.gz"
    _carmen_gz(path, 50 << 20)
    assert path.stat().st_size < 200 << 10
    first, grown = _probe(path)
    assert first.startswith("OctolgpError:"), first
    assert "bomb.log.gz:3: line longer than octolgp.io.limits.MAX_LINE_LENGTH" in first
    assert grown < 24 << 10, f"RSS grew by {grown} KiB"


def test_an_overlong_carmen_line_names_its_line_or_is_skipped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(limits, "MAX_LINE_LENGTH", 64)
    path = tmp_path / "long.log.gz"
    _carmen_gz(path, 1000)
    reader = CarmenReader(path)
    assert len(next(reader)) == 3
    with pytest.raises(OctolgpError, match=r"long\.log\.gz:3: line longer than .* \(64 char"):
        next(reader)
    skipping = CarmenReader(path, skip_bad=True)
    assert len(list(skipping)) == 2  # the lines on both sides of it
    assert skipping.bad_lines == [3]
    # A line of exactly the limit is read.
    exact = tmp_path / "exact.log"
    exact.write_text(CARMEN_LINE.rstrip("\n").ljust(63) + "\n")
    assert len(list(CarmenReader(exact, max_range=81.83))) == 1


def _ply_head(fmt: str, before: str = "", vertices: int = 2) -> bytes:
    return (
        f"ply\nformat {fmt} 1.0\n{before}element vertex {vertices}\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n"
    ).encode()


def test_ply_element_counts_of_1e12_are_refused_from_the_header(tmp_path: Path) -> None:
    path = tmp_path / "huge.ply"
    path.write_bytes(_ply_head("binary_little_endian", vertices=HUGE) + bytes(24))
    with pytest.raises(OctolgpError, match=rf"huge\.ply:3: element vertex claims {HUGE} points"):
        list(PlyReader(path))
    # A skipped element before the vertices: the count cannot fit in the file.
    for fmt, per in (("binary_little_endian", 4), ("ascii", 1)):
        path.write_bytes(_ply_head(fmt, f"element face {HUGE}\nproperty int a\n") + bytes(24))
        want = rf"huge\.ply: truncated .*element 'face' claims {HUGE} instances \(at least {per}"
        with pytest.raises(OctolgpError, match=want):
            list(PlyReader(path))
    # A list property: each instance holds at least its count byte.
    path.write_bytes(
        _ply_head("binary_little_endian", f"element face {HUGE}\nproperty list uchar int v\n")
    )
    with pytest.raises(OctolgpError, match=r"'face' claims \d+ instances \(at least 1 bytes"):
        list(PlyReader(path))


def test_text_scans_are_capped_as_they_are_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Compressed text has no header to check: the points and lines are counted as read."""
    monkeypatch.setattr(limits, "MAX_SCAN_POINTS", 50)
    rows = "".join(f"{i} 1 2\n" for i in range(80))
    dat = tmp_path / "s.dat.gz"
    dat.write_bytes(gzip.compress(rows.encode()))
    with pytest.raises(OctolgpError, match=r"s\.dat\.gz:\d+: the scan holds 80 points, more than"):
        list(ScanDatReader(dat))
    tdk = tmp_path / "scan000.3d"
    tdk.write_text(rows)
    (tmp_path / "scan000.pose").write_text("0 0 0\n0 0 0\n")
    with pytest.raises(OctolgpError, match=r"scan000\.3d:80: holds 80 points, more than"):
        list(ThreeDTKReader(tdk, pose="pose"))
    kitti = ROOT / "tests/data/kitti/sequences/00"
    with pytest.raises(OctolgpError, match=r"000000\.bin: the file claims \d+ points, more than"):
        list(load_scans(kitti))
    monkeypatch.setattr(limits, "MAX_SCAN_POINTS", 1 << 24)
    monkeypatch.setattr(limits, "MAX_LINE_LENGTH", 32)
    dat.write_bytes(gzip.compress(b"1 2 3\n" + b"4" * 100 + b" 5 6\n7 8 9\n"))
    with pytest.raises(OctolgpError, match=r"s\.dat\.gz:2: line longer than"):
        list(ScanDatReader(dat))
    skipped = ScanDatReader(dat, skip_bad=True)
    assert len(next(skipped)) == 2
    assert skipped.bad_lines == [(dat, 2)]
    tdk.write_text("1 2 3\n" + "4" * 100 + " 5 6\n7 8 9\n")
    with pytest.raises(OctolgpError, match=r"scan000\.3d:2: line longer than"):
        list(ThreeDTKReader(tdk, pose="pose"))
