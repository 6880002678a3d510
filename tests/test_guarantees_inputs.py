"""Inputs never lose or invent data: scans own their arrays, readers refuse what they cannot trust.

Each test is one way an input could silently change a map: a scan that aliases the
caller's buffer, a recording replayed from its lossy display copy, flipped bytes in a
recording, and files whose headers claim more data than any scan holds (decompression
bombs), which must be refused from the header before anything is read or inflated.
"""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest

from octolgp import Scan

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
