"""Inputs never lose or invent data: scans own their arrays, readers refuse what they cannot trust.

Each test is one way an input could silently change a map: a scan that aliases the
caller's buffer, a recording replayed from its lossy display copy, flipped bytes in a
recording, and files whose headers claim more data than any scan holds (decompression
bombs), which must be refused from the header before anything is read or inflated.
"""

from __future__ import annotations

import array
import logging
import re
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rerun as rr

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.io.rrd_read import read_rrd
from octolgp.io.rrd_write import log_scan
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
    config = MapConfig(dim=2, resolution=0.2, hyperparameters=HP)
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


def _same(got: Scan, want: Scan) -> None:
    np.testing.assert_array_equal(got.points, want.points)
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
            _same(scan, want)  # a prefix of the exact scans: max_range kept
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
        _same(scan, want)
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
