"""Rerun recordings: exact round trip, generic robot recordings, cut and killed files, errors."""

from __future__ import annotations

import logging
import math
import os
import re
import signal
import struct
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import SCAN_FORMATS, detect_format, load_scans
from octolgp.io.rrd_read import RrdScanReader, read_rrd
from octolgp.io.rrd_write import log_scan
from octolgp.scan import Scan

ROOT = Path(__file__).resolve().parents[1]

# Shared by the tests and the child process that is killed mid-recording.
SCANS_SOURCE = """
import numpy as np
from octolgp.scan import Scan

def make_scan(i):
    rng = np.random.default_rng(i)
    dim = 3 if i % 2 == 0 else 2
    origin = rng.normal(size=dim) * 10.0
    points = origin + rng.normal(size=(40 + i % 7, dim)) * 3.0
    max_range = None if i % 3 == 0 else 4.0 + 0.1 * i
    stamp = None if i % 4 == 1 else 1.7e9 + 0.1 * i + 1e-7
    return Scan(origin, points, max_range=max_range, stamp=stamp)
"""
_NS: dict[str, object] = {}
exec(SCANS_SOURCE, _NS)
make_scan: Callable[[int], Scan] = _NS["make_scan"]  # type: ignore[assignment]


def _recording(path: Path) -> rr.RecordingStream:
    rec = rr.RecordingStream("octolgp_test")
    rec.save(path)
    return rec


def _write(path: Path, scans: list[Scan], indices: list[int] | None = None) -> None:
    rec = _recording(path)
    for scan, i in zip(scans, indices or range(len(scans)), strict=True):
        log_scan(rec, scan, i)
        rec.flush()  # one chunk per entity and scan: many messages to cut between
    rec.disconnect()  # writes the End message and the footer


def _assert_same(got: list[Scan], want: list[Scan]) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.origin.dtype == np.float64
        assert a.points.dtype == np.float64
        assert np.array_equal(a.origin, b.origin)
        assert np.array_equal(a.points, b.points)
        assert a.max_range == b.max_range
        assert a.stamp == b.stamp


# --------------------------------------------------------------------------- exact round trip


def test_log_scan_round_trip_is_bit_identical(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(12)]
    assert {s.dim for s in scans} == {2, 3}
    assert {s.stamp is None for s in scans} == {True, False}
    assert {s.max_range is None for s in scans} == {True, False}
    path = tmp_path / "run.rrd"
    _write(path, scans)
    assert "rrd" in SCAN_FORMATS
    assert detect_format(path) == "rrd"
    reader = load_scans(path)
    assert isinstance(reader, RrdScanReader)
    assert reader.exact
    assert reader.timeline == "scan"
    assert reader.count == 12
    _assert_same(list(reader), scans)
    assert reader.closed
    assert reader.skipped == 0
    assert reader.notes == []


def test_round_trip_in_timeline_order_and_by_magic(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(6)]
    path = tmp_path / "shuffled.bin"  # no .rrd suffix: found by the RRF2 magic bytes
    _write(path, [scans[i] for i in (3, 0, 5, 1, 4, 2)], [3, 0, 5, 1, 4, 2])
    assert detect_format(path) == "rrd"
    _assert_same(list(load_scans(path)), scans)
    _assert_same(list(load_scans(path, format="rrd")), scans)


def test_log_scan_layout_for_the_viewer(tmp_path: Path) -> None:
    """The robot-style entities replay as world points (float32) without octolgp/scan."""
    scans = [make_scan(i) for i in range(4)]
    path = tmp_path / "run.rrd"
    _write(path, scans)
    reader = read_rrd(path, points="world/sensor/points")
    assert not reader.exact
    assert reader.pose_entity == "/world/sensor/points"
    got = list(reader)
    assert len(got) == 4
    for a, b in zip(got, scans, strict=True):
        assert a.dim == b.dim
        np.testing.assert_allclose(a.origin, b.origin, atol=1e-5)
        np.testing.assert_allclose(a.points, b.points, atol=1e-5)
    # The "time" timeline holds only the stamped scans, in seconds.
    timed = list(read_rrd(path, points="world/sensor/points", timeline="time"))
    stamped = [s for s in scans if s.stamp is not None]
    assert [s.stamp for s in timed] == pytest.approx([s.stamp for s in stamped], abs=1e-6)


# --------------------------------------------------------------------------- generic recordings


def _quat_z(theta: float) -> list[float]:
    return [0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)]


def _rot_z(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


FRAMES = 6


def _robot_recording(path: Path, *, points2d: bool = False, extra: bool = False) -> list[dict]:
    """Log a robot the way any program would: raw rerun calls, no octolgp/scan.

    ``world/robot`` moves (translation + quaternion, every frame but the 3rd); the laser sits
    on it with a static mount (translation + axis-angle); the points are in the laser frame.
    """
    rng = np.random.default_rng(7)
    rec = _recording(path)
    mount_t = np.array([0.2, 0.0, 0.5])
    mount_R = _rot_x(0.3) if not points2d else np.eye(3)
    rec.log(
        "world/robot/laser",
        rr.Transform3D(
            translation=mount_t,
            rotation_axis_angle=rr.RotationAxisAngle(axis=[1, 0, 0], radians=0.3)
            if not points2d
            else None,
        ),
        static=True,
    )
    truth: list[dict] = []
    pose_t, pose_R = np.zeros(3), np.eye(3)
    for f in range(FRAMES):
        rec.set_time("frame", sequence=f)
        rec.set_time("time", timestamp=1.7e9 + f)
        if f != 2:  # frame 2 has no new pose: latest-at uses frame 1's
            theta = 0.4 * f
            pose_t = np.array([1.0 + f, -2.0 + 0.5 * f, 0.1 * f])
            pose_R = _rot_z(theta)
            rec.log("world/robot", rr.Transform3D(translation=pose_t, quaternion=_quat_z(theta)))
        local = rng.normal(size=(30, 2 if points2d else 3)) * 4.0
        if points2d:
            rec.log("world/robot/laser", rr.Points2D(local))
            local3 = np.concatenate([local, np.zeros((30, 1))], axis=1)
        else:
            rec.log("world/robot/laser", rr.Points3D(local))
            local3 = local
        if extra:
            rec.log("debug/cloud", rr.Points3D(rng.normal(size=(5, 3))))
        R = pose_R @ mount_R
        t = pose_R @ mount_t + pose_t
        truth.append({"origin": t, "points": local3 @ R.T + t, "R": R, "t": t, "stamp": 1.7e9 + f})
    rec.disconnect()
    return truth


def test_generic_points3d_composes_latest_poses(tmp_path: Path) -> None:
    path = tmp_path / "robot.rrd"
    truth = _robot_recording(path)
    reader = load_scans(path)
    assert isinstance(reader, RrdScanReader)
    assert not reader.exact
    assert reader.entity == "/world/robot/laser"
    assert reader.timeline == "frame"
    got = list(reader)
    assert len(got) == FRAMES
    for scan, want in zip(got, truth, strict=True):
        assert scan.dim == 3
        assert scan.max_range is None
        np.testing.assert_allclose(scan.origin, want["origin"], atol=1e-5)
        np.testing.assert_allclose(scan.points, want["points"], atol=1e-5)
        assert scan.stamp == pytest.approx(want["stamp"])


def test_generic_points2d_with_3d_pose(tmp_path: Path) -> None:
    path = tmp_path / "robot2d.rrd"
    truth = _robot_recording(path, points2d=True)
    got = list(read_rrd(path, max_range=8.0))
    assert len(got) == FRAMES
    for scan, want in zip(got, truth, strict=True):
        assert scan.dim == 2
        assert scan.max_range == 8.0
        np.testing.assert_allclose(scan.origin, want["origin"][:2], atol=1e-5)
        np.testing.assert_allclose(scan.points, want["points"][:, :2], atol=1e-5)


def _rot_axis(axis: list[float], angle: float) -> np.ndarray:
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


_R = _rot_axis([1.0, 2.0, 3.0], 0.7)
_T = np.array([1.5, -2.0, 0.25])
_HALF = 0.35
_K = np.array([1.0, 2.0, 3.0]) / np.linalg.norm([1.0, 2.0, 3.0])
_XYZW = [*(_K * math.sin(_HALF)), math.cos(_HALF)]
_INV = np.linalg.inv(np.block([[_R, _T[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))


@pytest.mark.parametrize(
    ("transform", "R", "t"),
    [
        (lambda: rr.Transform3D(translation=_T, mat3x3=_R), _R, _T),
        (lambda: rr.Transform3D(translation=_T, quaternion=rr.Quaternion(xyzw=_XYZW)), _R, _T),
        (
            lambda: rr.Transform3D(
                translation=_T,
                rotation=rr.RotationAxisAngle(axis=[1.0, 2.0, 3.0], degrees=math.degrees(0.7)),
            ),
            _R,
            _T,
        ),
        (lambda: rr.Transform3D(translation=_T, scale=2.0), 2.0 * np.eye(3), _T),
        (
            lambda: rr.Transform3D(
                translation=_T, mat3x3=_R, relation=rr.TransformRelation.ChildFromParent
            ),
            _INV[:3, :3],
            _INV[:3, 3],
        ),
    ],
    ids=["mat3x3", "quaternion", "axis-angle", "scale", "child-from-parent"],
)
def test_every_transform_form(
    tmp_path: Path, transform: Callable[[], rr.Transform3D], R: np.ndarray, t: np.ndarray
) -> None:
    path = tmp_path / "form.rrd"
    local = np.random.default_rng(3).normal(size=(20, 3))
    rec = _recording(path)
    rec.set_time("frame", sequence=0)
    rec.log("sensor", transform())
    rec.log("sensor", rr.Points3D(local))
    rec.disconnect()
    (scan,) = list(read_rrd(path))
    np.testing.assert_allclose(scan.origin, t, atol=1e-5)
    np.testing.assert_allclose(scan.points, local @ R.T + t, atol=1e-5)


def test_ambiguous_recording_names_every_candidate(tmp_path: Path) -> None:
    path = tmp_path / "two.rrd"
    rec = _recording(path)
    rec.set_time("frame", sequence=0)
    rec.log("a/lidar", rr.Points3D([[1.0, 2.0, 3.0]]))
    rec.log("b/lidar", rr.Points3D([[1.0, 2.0, 3.0]]))
    rec.disconnect()
    with pytest.raises(OctolgpError, match="several points entities") as info:
        read_rrd(path)
    assert "/a/lidar" in str(info.value)
    assert "/b/lidar" in str(info.value)
    assert str(path) in str(info.value)
    assert len(list(read_rrd(path, points="b/lidar"))) == 1


def test_prefers_the_points_entity_under_a_transform(tmp_path: Path) -> None:
    path = tmp_path / "robot.rrd"
    _robot_recording(path, extra=True)  # adds /debug/cloud, with no Transform3D above it
    reader = read_rrd(path)
    assert reader.entity == "/world/robot/laser"
    assert any("/debug/cloud" in n for n in reader.notes)


def test_generic_explicit_options(tmp_path: Path) -> None:
    path = tmp_path / "robot.rrd"
    truth = _robot_recording(path, extra=True)
    # The laser, ordered on the "time" timeline.
    reader = read_rrd(path, points="world/robot/laser", timeline="time")
    assert reader.timeline == "time"
    got = list(reader)
    assert len(got) == FRAMES
    for scan, want in zip(got, truth, strict=True):
        np.testing.assert_allclose(scan.points, want["points"], atol=1e-5)
        assert scan.stamp == pytest.approx(want["stamp"])
    # pose= names the robot: its frame (without the laser mount) is the sensor frame.
    robot = list(read_rrd(path, points="/world/robot/laser/", pose="world/robot"))
    assert len(robot) == FRAMES
    mount_t = np.array([0.2, 0.0, 0.5])
    for scan, want in zip(robot, truth, strict=True):
        robot_R = want["R"] @ _rot_x(0.3).T
        robot_t = want["t"] - robot_R @ mount_t
        np.testing.assert_allclose(scan.origin, robot_t, atol=1e-5)
        local = (want["points"] - want["t"]) @ want["R"]  # back to the laser frame
        np.testing.assert_allclose(scan.points, local @ robot_R.T + robot_t, atol=1e-5)
    # A points entity without any pose: world-frame points, origin 0, and a note.
    cloud = read_rrd(path, points="debug/cloud")
    assert all(np.array_equal(s.origin, np.zeros(3)) for s in cloud)
    assert any("no Transform3D" in n for n in cloud.notes)


def test_missing_entity_timeline_or_pose(tmp_path: Path) -> None:
    path = tmp_path / "robot.rrd"
    _robot_recording(path)
    with pytest.raises(OctolgpError, match="no entity '/nope'"):
        read_rrd(path, points="nope")
    with pytest.raises(OctolgpError, match="logs no Points3D"):
        read_rrd(path, points="world/robot")
    with pytest.raises(OctolgpError, match="not on timeline 'tick'"):
        read_rrd(path, timeline="tick")
    with pytest.raises(OctolgpError, match="no pose entity '/elsewhere'"):
        read_rrd(path, pose="elsewhere")
    with pytest.raises(OctolgpError, match="no octolgp/scan records"):
        read_rrd(path, points="octolgp/scan")


# --------------------------------------------------------------------------- cut and killed files


def _prefix_length(got: list[Scan], want: list[Scan]) -> int:
    """Check that ``got`` is a prefix of ``want`` (bit-identical) and return its length."""
    _assert_same(got, want[: len(got)])
    return len(got)


def test_truncated_recording_replays_the_complete_prefix(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(16)]
    path = tmp_path / "full.rrd"
    _write(path, scans)
    data = path.read_bytes()
    counts = []
    for fraction in (0.3, 0.55, 0.8, 0.97):
        cut = tmp_path / f"cut{fraction}.rrd"
        at = int(len(data) * fraction) + 3
        cut.write_bytes(data[:at])
        reader = read_rrd(cut)
        got = list(reader)
        if reader.skipped_bytes == 0:
            # The cut fell on a message boundary (message sizes vary with ids and stamps);
            # one byte further is inside the next message's header.
            cut.write_bytes(data[: at + 1])
            reader = read_rrd(cut)
            got = list(reader)
        counts.append(_prefix_length(got, scans))
        assert reader.closed == (len(got) == len(scans))  # only a cut footer keeps all
        assert reader.skipped_bytes > 0
        assert any("incomplete" in n for n in reader.notes)
        # The generic reading of the same file is a prefix too, and every scan has its pose.
        generic = list(read_rrd(cut, points="world/sensor/points"))
        assert 0 < len(generic) <= len(scans)
        for a, b in zip(generic, scans, strict=False):
            np.testing.assert_allclose(a.points, b.points, atol=1e-5)
    # The last cut falls in the footer (the chunk manifest): every scan is complete.
    assert counts == sorted(counts)
    assert counts[0] > 0
    assert counts[-2] < counts[-1] == len(scans)
    # Cut in the header or in the first message: nothing complete.
    for n in (0, 3, 8, 20):
        cut = tmp_path / f"head{n}.rrd"
        cut.write_bytes(data[:n])
        with pytest.raises(OctolgpError, match=re.escape(str(cut))):
            read_rrd(cut)


def test_cut_recording_logs_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "full.rrd"
    _write(path, [make_scan(i) for i in range(4)])
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2 + 3])
    with caplog.at_level(logging.WARNING, logger="octolgp"):
        list(read_rrd(cut))
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(cut) in m and "not closed" in m for m in warned), warned
    assert any(str(cut) in m and "incomplete" in m for m in warned), warned
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="octolgp"):
        list(read_rrd(path))
    assert not caplog.records  # a closed, complete recording: nothing to warn about


def test_recording_of_a_killed_writer(tmp_path: Path) -> None:
    """SIGKILL mid-run: every scan flushed before the kill replays, bit-identical.

    What reaches the file: ``rec.log`` only queues a row in rerun's batcher; the batcher
    writes a chunk per entity when its size/row/time thresholds trip, and ``rec.flush()``
    returns once the pending chunks are written to the file. So after a SIGKILL the file
    holds every scan flushed before it and no End message or footer; the reader replays it
    (rerun 0.41 reads footer-less files, with a RerunWarning that the reader records).
    """
    path = tmp_path / "killed.rrd"
    child = tmp_path / "child.py"
    child.write_text(
        SCANS_SOURCE
        + """
import sys, time
import rerun as rr
from octolgp.io.rrd_write import log_scan

rec = rr.RecordingStream("octolgp_killed")
rec.save(sys.argv[1])
for i in range(100000):
    log_scan(rec, make_scan(i), i)
    rec.flush()
    print(i, flush=True)
    time.sleep(0.001)
"""
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, str(child), str(path)], stdout=subprocess.PIPE, text=True, env=env
    )
    assert proc.stdout is not None
    flushed = -1
    for line in proc.stdout:
        flushed = int(line)
        if flushed >= 24:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    assert flushed >= 24
    reader = read_rrd(path)
    got = list(reader)
    assert len(got) >= flushed + 1  # everything flushed before the kill
    _prefix_length(got, [make_scan(i) for i in range(len(got))])
    assert not reader.closed
    assert any("did not close" in n for n in reader.notes)


def test_open_recording_and_scans_after_the_last_pose(tmp_path: Path) -> None:
    """Read while the writer is still open (no footer); latest-at vs. a possibly lost pose."""
    path = tmp_path / "open.rrd"
    rec = _recording(path)
    for f in range(6):
        rec.set_time("frame", sequence=f)
        if f < 4:  # frames 4 and 5 have no pose of their own
            rec.log("robot", rr.Transform3D(translation=[float(f), 0.0, 0.0]))
        rec.log("robot/lidar", rr.Points3D([[1.0, 0.0, 0.0]]))
        rec.flush()
    # Not closed: the poses of frames 4 and 5 may still be on their way, so those are dropped.
    reader = read_rrd(path)
    assert not reader.closed
    assert [s.origin[0] for s in reader] == [0.0, 1.0, 2.0, 3.0]
    assert reader.skipped == 2
    assert any("after the last pose" in n for n in reader.notes)
    rec.disconnect()
    # Closed: latest-at gives frames 4 and 5 the pose of frame 3.
    closed = read_rrd(path)
    assert closed.closed
    assert [s.origin[0] for s in closed] == [0.0, 1.0, 2.0, 3.0, 3.0, 3.0]
    assert [s.points[0, 0] for s in read_rrd(path)] == [1.0, 2.0, 3.0, 4.0, 4.0, 4.0]


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "content",
    [
        b"",
        b"hello world\nthis is text\n",
        bytes(4096),
        b"\x89PNG\r\n\x1a\n" + bytes(64),
        b"RRF1" + bytes(64),
        b"RRF2\x00)\x00\x00\x01\x02\x00\x00" + b"\x07" * 40,
    ],
    ids=["empty", "text", "zeros", "png", "legacy", "bad-message"],
)
def test_foreign_files_raise_naming_the_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.rrd"
    path.write_bytes(content)
    with pytest.raises(OctolgpError, match=r"x\.rrd"):
        list(load_scans(path))
    with pytest.raises(OctolgpError, match=r"x\.rrd"):
        read_rrd(path)


def _message_starts(data: bytes) -> list[int]:
    """Offsets of the messages of a one-stream RRD file (12-byte header, u64 kind, u64 len)."""
    starts, off = [], 12
    while off + 16 <= len(data):
        kind, length = struct.unpack_from("<QQ", data, off)
        if kind == 0:
            break
        starts.append(off)
        off += 16 + length
    return starts


def test_corrupt_payload_and_invalid_records(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(6)]
    path = tmp_path / "ok.rrd"
    _write(path, scans)
    data = bytearray(path.read_bytes())
    starts = _message_starts(bytes(data))
    mid = starts[len(starts) // 2] + 16
    data[mid : mid + 32] = b"\xff" * 32  # the payload's protobuf: undecodable, framing intact
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(bytes(data))
    with pytest.raises(OctolgpError, match=re.escape(str(bad))):
        list(read_rrd(bad))
    partial = read_rrd(bad, skip_bad=True)  # the chunks before the bad message
    got = list(partial)
    assert 0 < len(got) < len(scans)
    _assert_same(got, scans[: len(got)])
    assert any("stopped" in n for n in partial.notes)
    # An octolgp/scan record that is no valid scan: raise, or skip with skip_bad.
    odd = tmp_path / "odd.rrd"
    rec = _recording(odd)
    log_scan(rec, scans[0], 0)
    rec.set_time("scan", sequence=1)
    rec.log(
        "octolgp/scan",
        rr.DynamicArchetype(
            "octolgp.Scan",
            components={"origin": np.zeros(3), "points": np.zeros(4), "dim": np.array([3])},
        ),
    )
    log_scan(rec, scans[2], 2)
    rec.disconnect()
    with pytest.raises(OctolgpError, match="scan=1"):
        list(read_rrd(odd))
    reader = read_rrd(odd, skip_bad=True)
    _assert_same(list(reader), [scans[0], scans[2]])
    assert reader.skipped == 1


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MapFileNotFound):
        read_rrd(tmp_path / "nope.rrd")
    with pytest.raises(MapFileNotFound):
        load_scans(tmp_path / "nope.rrd")


def test_recording_without_scans(tmp_path: Path) -> None:
    path = tmp_path / "scalars.rrd"
    rec = _recording(path)
    for i in range(3):
        rec.set_time("step", sequence=i)
        rec.log("loss", rr.Scalars(1.0 / (i + 1)))
    rec.log("map", rr.Points3D([[0.0, 0.0, 0.0]]), static=True)
    rec.disconnect()
    with pytest.raises(OctolgpError, match="no Points3D/Points2D entity") as info:
        load_scans(path)
    assert "/map" in str(info.value)  # the static cloud is named, but is no scan
