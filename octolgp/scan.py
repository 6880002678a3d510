"""Range scans in the world frame: the input of every map."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.ros_msgs import laserscan_beams, pointcloud2_points, stamp_seconds

FloatArray = NDArray[np.float64]


def as_points(
    value: object, name: str, dim: int | None = None, *, copy: bool = False
) -> FloatArray:
    """Validate an ``(n, d)`` array of finite coordinates and return it as float64.

    Parameters
    ----------
    value : array_like
        Candidate array.
    name : str
        Field name used in the error message.
    dim : int, optional
        Required second dimension (2 or 3); any of 1, 2, 3 when omitted.
    copy : bool, default False
        Always return a new array that shares no memory with ``value``. Otherwise a
        C-contiguous float64 ``value`` is returned as is.

    Raises
    ------
    OctolgpError
        On a wrong type, shape, non-numeric dtype or a non-finite value.
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:
        raise OctolgpError(f"{name} is not an array: {exc}") from None
    if arr.dtype.kind not in "iuf":
        raise OctolgpError(f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.ndim != 2 or (dim is not None and arr.shape[1] != dim) or arr.shape[1] not in (1, 2, 3):
        want = f"(n, {dim})" if dim is not None else "(n, d) with d in 1..3"
        raise OctolgpError(f"{name} must have shape {want}, got {arr.shape}")
    if copy:
        out = np.array(arr, dtype=np.float64, order="C", copy=True)
    else:
        out = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(out).all():
        raise OctolgpError(f"{name} contains NaN or inf")
    return out


NO_RETURN_RTOL = 1e-9
"""A beam at least ``max_range * (1 - NO_RETURN_RTOL)`` long is a no-return (a range
reported at exactly ``max_range`` must not round into a hit)."""


def scan_steps(scan: Scan, precision: float) -> NDArray[np.int64]:
    """Each beam's offset from the sensor in whole steps of ``precision`` metres.

    A return's step is ``round((point - origin) / precision)`` per axis. A beam whose
    rounded length would cross ``max_range * (1 - NO_RETURN_RTOL)`` (a no-return that
    would shrink into a hit, or a return that would grow into a no-return) is rounded
    one step further out (no-returns) or in (returns) along its own direction, so no
    beam changes kind; it then moves by at most two steps. Lengths are decided on the
    integer steps with a margin of a hundredth of a step, so rounding the rounded scan
    gives the same steps.

    Returns
    -------
    ndarray of int64, shape (n, d)
    """
    offset = scan.points - scan.origin
    steps = np.round(offset / precision)
    if scan.max_range is not None:
        limit = scan.max_range * (1.0 - NO_RETURN_RTOL)
        margin = 0.01 * precision
        length = np.linalg.norm(offset, axis=1)
        after = np.linalg.norm(steps, axis=1) * precision
        no_return = length >= limit
        out = no_return & (after < limit + margin)
        inward = ~no_return & (after > limit - margin)
        for moved, sign in ((out, 1.0), (inward, -1.0)):  # two passes, vectorised
            if moved.any():
                r = length[moved, None]
                steps[moved] = np.round(offset[moved] / r * (r + sign * precision) / precision)
    return steps.astype(np.int64)


def points_from_steps(origin: FloatArray, steps: NDArray[np.int64], precision: float) -> FloatArray:
    """Inverse of :func:`scan_steps`: ``origin + steps * precision``, (n, d) float64."""
    out: FloatArray = origin + steps.astype(np.float64) * precision
    return out


def canonical_order(steps: NDArray[np.int64]) -> NDArray[np.intp]:
    """The order of a rounded scan's beams by their steps, the last axis (height) first.

    A map with ``scan_precision`` is built from its scans' beams in this order, which
    is a function of the beams alone: the journal stores them sorted, where
    neighbouring beams' steps differ least.
    """
    order: NDArray[np.intp] = np.lexsort(steps.T)
    return order


def check_scan_size(scan: Scan, limit: int, field: str = "OnlineConfig.max_scan_points") -> None:
    """Refuse a scan with more than ``limit`` points, naming the setting that raises it.

    Raises
    ------
    OctolgpError
        If ``len(scan) > limit``.
    """
    if len(scan) > limit:
        raise OctolgpError(
            f"scan has {len(scan)} points, more than {field} ({limit}): "
            f"downsample it (Scan.downsample) or raise {field}"
        )


ROTATION_TOLERANCE = 1e-3
"""Largest ``|RᵀR - I|`` entry of a sensor rotation kept as the nearest rotation: pose
files print a few digits, and their matrices and quaternions are that far from one."""


def nearest_rotation(value: object, dim: int, name: str) -> FloatArray:
    """The rotation nearest to a ``(dim, dim)`` matrix within :data:`ROTATION_TOLERANCE` of one.

    The nearest rotation in the Frobenius norm, ``U Vᵀ`` of the SVD ``R = U S Vᵀ``
    (the orthogonal Procrustes solution).

    Raises
    ------
    OctolgpError
        Naming ``name``: not numeric, the wrong shape, NaN or inf, a reflection
        (``det < 0``) or further than the tolerance from a rotation.
    """
    try:
        R = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise OctolgpError(f"{name} is not a numeric matrix: {exc}") from None
    if R.shape != (dim, dim):
        raise OctolgpError(f"{name} must have shape ({dim}, {dim}), got {R.shape}")
    if not np.isfinite(R).all():
        raise OctolgpError(f"{name} contains NaN or inf")
    off = float(np.abs(R.T @ R - np.eye(dim)).max())
    det = float(np.linalg.det(R))
    if off > ROTATION_TOLERANCE or det <= 0:
        raise OctolgpError(
            f"{name} is not a rotation: |RᵀR - I| = {off:.2g} (at most {ROTATION_TOLERANCE:g}) "
            f"and det = {det:.6g} (> 0)"
        )
    if off <= 1e-12 and abs(det - 1.0) <= 1e-12:  # a rotation to rounding: kept bit for bit
        return R
    U, _, Vt = np.linalg.svd(R)
    out: FloatArray = U @ Vt
    return out


def planar_rotation(yaw: float, dim: int) -> FloatArray:
    """The rotation by ``yaw`` radians (CCW) about z, ``(dim, dim)`` (2 or 3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.eye(dim)
    R[:2, :2] = [[c, -s], [s, c]]
    return R


def pose_rotation(pose: ArrayLike, dim: int) -> FloatArray:
    """The rotation of a sensor pose as :mod:`octolgp.ros_msgs` takes it, ``(dim, dim)``.

    ``(x, y, theta)`` turns by ``theta`` about z; a 3x3 or 4x4 homogeneous matrix gives
    its rotation block (a 3x3 one's, in a 3D scan, about z). The pose has been checked.
    """
    p = np.asarray(pose, dtype=np.float64)
    if p.shape == (3,):
        return planar_rotation(float(p[2]), dim)
    if p.shape == (3, 3) and dim == 3:
        return planar_rotation(float(np.arctan2(p[1, 0], p[0, 0])), 3)
    out: FloatArray = p[:dim, :dim].copy()
    return out


@dataclass(frozen=True, eq=False)
class Scan:
    """One range scan, in the world frame.

    Parameters
    ----------
    origin : array_like of shape (d,)
        Sensor position in the world frame, metres. ``d`` is 2 or 3.
    points : array_like of shape (n, d)
        Beam endpoints in the world frame, metres, ``n >= 1``.
    max_range : float, optional
        A beam at least this long is a no-return: free space up to ``max_range``
        along it and no hit.
    stamp : float, optional
        Time, seconds.
    rotation : array_like of shape (d, d), optional
        The sensor frame's orientation in the world frame (its axes as columns), so
        that ``[[rotation, origin], [0, 1]]`` is the pose the scan was taken from
        (:attr:`pose`). The map is built from ``origin`` and ``points`` alone; the map
        journal keeps the rotation so that a pose graph's new absolute poses can be
        applied later (:meth:`octolgp.OnlineMap.correct_poses`). A matrix within
        :data:`ROTATION_TOLERANCE` of a rotation is kept as the nearest rotation.
        :meth:`from_ranges`, :meth:`from_laserscan` and :meth:`from_pointcloud2` set it.

    Raises
    ------
    OctolgpError
        On a wrong shape, a non-finite value, an empty scan, a non-positive
        ``max_range``, or a ``rotation`` that is not a rotation (a reflection, a scale,
        a shear).

    Notes
    -----
    The scan keeps read-only float64 copies of ``origin`` and ``points``: changing or
    reusing the caller's arrays afterwards never changes the scan, and the caller's
    arrays stay writeable.
    """

    origin: FloatArray
    points: FloatArray
    max_range: float | None = None
    stamp: float | None = None
    rotation: FloatArray | None = None

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin) if not isinstance(self.origin, np.ndarray) else self.origin
        if origin.ndim != 1 or origin.shape[0] not in (2, 3):
            raise OctolgpError(f"Scan.origin must have shape (2,) or (3,), got {origin.shape}")
        # A scan owns copies of its arrays: it freezes them and keeps them, so it must
        # never keep (nor freeze) memory the caller can still write, such as a buffer a
        # robot loop refills for every scan.
        origin = as_points(origin[None, :], "Scan.origin", copy=True)[0]
        points = as_points(self.points, "Scan.points", dim=origin.shape[0], copy=True)
        if points.shape[0] == 0:
            raise OctolgpError("Scan.points is empty: a scan needs at least one beam")
        if self.max_range is not None:
            mr = self.max_range
            if isinstance(mr, bool) or not isinstance(mr, int | float | np.floating | np.integer):
                raise OctolgpError(f"Scan.max_range must be a number, got {mr!r}")
            if not np.isfinite(mr) or mr <= 0:
                raise OctolgpError(f"Scan.max_range must be finite and > 0, got {mr!r}")
            object.__setattr__(self, "max_range", float(mr))
        if self.stamp is not None:
            st = self.stamp
            if isinstance(st, bool) or not isinstance(st, int | float | np.floating | np.integer):
                raise OctolgpError(f"Scan.stamp must be a number, got {st!r}")
            if not np.isfinite(st):
                raise OctolgpError(f"Scan.stamp must be finite, got {st!r}")
            object.__setattr__(self, "stamp", float(st))
        if self.rotation is not None:
            rotation = nearest_rotation(self.rotation, origin.shape[0], "Scan.rotation")
            rotation.setflags(write=False)
            object.__setattr__(self, "rotation", rotation)
        origin.setflags(write=False)
        points.setflags(write=False)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "points", points)

    @property
    def dim(self) -> int:
        """Spatial dimension, 2 or 3."""
        return int(self.origin.shape[0])

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def pose(self) -> FloatArray | None:
        """The sensor's pose, a ``(d+1, d+1)`` homogeneous matrix (sensor to world frame).

        ``None`` when the scan was made without its :attr:`rotation`.
        """
        if self.rotation is None:
            return None
        d = self.dim
        T = np.eye(d + 1)
        T[:d, :d], T[:d, d] = self.rotation, self.origin
        return T

    @classmethod
    def from_ranges(
        cls,
        pose: ArrayLike,
        ranges: ArrayLike,
        angles: ArrayLike,
        max_range: float | None = None,
        stamp: float | None = None,
    ) -> Scan:
        """Build a 2D scan from a planar laser's ranges.

        Parameters
        ----------
        pose : array_like of shape (3,)
            Laser pose ``(x, y, theta)`` in the world frame: metres, radians CCW.
        ranges : array_like of shape (n,)
            Ranges, metres.
        angles : array_like of shape (n,)
            Beam angles in the laser frame, radians CCW from its x axis.
        max_range : float, optional
            No-return threshold, metres.
        stamp : float, optional
            Time, seconds.

        Raises
        ------
        OctolgpError
            On mismatched shapes, non-finite values or negative ranges.
        """
        p = np.asarray(pose, dtype=np.float64)
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise OctolgpError(f"Scan.from_ranges: pose must be 3 finite numbers, got {p.shape}")
        if r.ndim != 1 or a.shape != r.shape:
            raise OctolgpError(
                f"Scan.from_ranges: ranges {r.shape} and angles {a.shape} must be equal 1D shapes"
            )
        if not (np.isfinite(r).all() and np.isfinite(a).all()):
            raise OctolgpError("Scan.from_ranges: ranges or angles contain NaN or inf")
        if (r < 0).any():
            raise OctolgpError("Scan.from_ranges: ranges must be >= 0")
        phi = p[2] + a
        pts = p[:2] + r[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        return cls(p[:2], pts, max_range, stamp, planar_rotation(float(p[2]), 2))

    @classmethod
    def from_laserscan(
        cls,
        msg: Any,
        pose: ArrayLike,
        *,
        max_range: float | None = None,
        stamp: float | None = None,
    ) -> Scan:
        """Build a scan from a ROS 2 ``sensor_msgs/msg/LaserScan``.

        The message may come from ``rclpy``, from ``rosbags`` or be any object with the
        fields ``angle_min``, ``angle_increment``, ``ranges``, ``range_min``, ``range_max``
        (``angle_max`` and ``header.stamp`` are used when present). A reading in
        ``[range_min, range_max)`` is a hit; ``+inf`` or ``>= range_max`` is a no-return (a
        beam of length ``range_max``, :attr:`max_range` 1 mm below it); ``NaN``, ``-inf``
        and readings below ``range_min`` are dropped (REP 117). The decoder is the ROS bag
        reader's (:mod:`octolgp.ros_msgs`).

        Parameters
        ----------
        msg : sensor_msgs/msg/LaserScan
            The scan, ranges in metres, angles in radians in the laser frame.
        pose : array_like of shape (3,), (3, 3) or (4, 4)
            The laser frame's pose in the world frame: ``(x, y, theta)`` (metres, radians
            CCW) or a 3x3 homogeneous matrix give a 2D scan; a 4x4 matrix gives a 3D scan
            whose beams lie in the laser's xy plane.
        max_range : float, optional
            Metres; the no-return threshold used instead of ``range_max`` when smaller.
        stamp : float, optional
            Seconds; default: ``msg.header.stamp`` (``None`` if absent or zero).

        Raises
        ------
        OctolgpError
            On a malformed message (naming the field: ``Scan.from_laserscan:
            angle_increment must be > 0, got 0.0``), a bad pose (shape, NaN or inf, not
            rigid), or a scan with no beam left.
        """
        try:
            beams = laserscan_beams(msg, pose, max_range=max_range)
            stamp = stamp_seconds(msg) if stamp is None else stamp
        except OctolgpError as exc:
            raise OctolgpError(f"Scan.from_laserscan: {exc}") from None
        if beams is None:
            raise OctolgpError(
                "Scan.from_laserscan: no beam left (every range is NaN, -inf or below range_min)"
            )
        return cls(*beams, stamp, pose_rotation(pose, beams[0].shape[0]))

    @classmethod
    def from_pointcloud2(
        cls,
        msg: Any,
        pose: ArrayLike,
        *,
        max_range: float | None = None,
        stamp: float | None = None,
    ) -> Scan:
        """Build a 3D scan from a ROS 2 ``sensor_msgs/msg/PointCloud2``.

        The message may come from ``rclpy``, from ``rosbags`` or be any object with the
        fields ``fields`` (``name``, ``offset``, ``datatype``, ``count``), ``point_step``,
        ``row_step``, ``data``, ``is_bigendian``, ``height`` and ``width``. ``x``, ``y``,
        ``z`` may be FLOAT32 or FLOAT64 at any offsets, in either byte order, among any
        other fields; rows may be padded to ``row_step``. Points with a NaN or inf
        coordinate (the holes of an organised cloud) are dropped. The decoder is the ROS bag
        reader's (:mod:`octolgp.ros_msgs`).

        Parameters
        ----------
        msg : sensor_msgs/msg/PointCloud2
            The cloud, metres, in the sensor frame.
        pose : array_like of shape (4, 4) or (3,)
            The sensor frame's pose in the world frame: a 4x4 homogeneous matrix, or
            ``(x, y, theta)`` for a sensor at z = 0 turned by ``theta`` about z.
        max_range : float, optional
            Metres; points at least this far from the sensor are no-returns. Default: none.
        stamp : float, optional
            Seconds; default: ``msg.header.stamp`` (``None`` if absent or zero).

        Raises
        ------
        OctolgpError
            On a malformed message (naming the field: ``Scan.from_pointcloud2: field 'z' at
            offset 8 overruns point_step 8``), a bad pose, or a cloud with no finite point.
        """
        try:
            points = pointcloud2_points(msg, pose, max_range=max_range)
            stamp = stamp_seconds(msg) if stamp is None else stamp
        except OctolgpError as exc:
            raise OctolgpError(f"Scan.from_pointcloud2: {exc}") from None
        if points is None:
            raise OctolgpError("Scan.from_pointcloud2: no finite point in the cloud")
        return cls(*points, stamp, pose_rotation(pose, 3))

    def rounded(self, precision: float) -> Scan:
        """The scan on a grid of ``precision`` steps from the sensor, beams in canonical order.

        Each return moves by at most half a step per axis; a beam that rounding would
        carry across ``max_range`` (a no-return that would become a hit, or the reverse)
        is rounded a step further along its own direction instead (see
        :func:`scan_steps`), so every beam keeps its kind. The beams are then sorted by
        their steps (:func:`canonical_order`). Rounding a rounded scan returns it
        unchanged, bit for bit.

        Parameters
        ----------
        precision : float
            Step, metres (> 0).
        """
        steps = scan_steps(self, precision)
        steps = steps[canonical_order(steps)]
        points = points_from_steps(self.origin, steps, precision)
        return Scan(self.origin, points, self.max_range, self.stamp, self.rotation)

    def downsample(self, voxel: float) -> Scan:
        """Keep one endpoint per voxel of edge ``voxel`` (a voxel-grid filter).

        This is the voxel-grid filter that OctoMap users put in front of
        ``insertPointCloud`` (PCL's ``VoxelGrid``), except that the kept point is
        the voxel's first endpoint rather than its centroid, so every kept beam is
        a real beam. No-returns (beams at least ``max_range`` long) are filtered
        separately from returns, so a no-return never replaces a hit.

        Parameters
        ----------
        voxel : float
            Voxel edge, metres, > 0.

        Returns
        -------
        Scan
            The same origin, ``max_range``, ``stamp`` and ``rotation``, fewer points, in
            their original order.
        """
        if isinstance(voxel, bool) or not isinstance(voxel, int | float | np.floating | np.integer):
            raise OctolgpError(f"Scan.downsample: voxel must be a number, got {voxel!r}")
        if not np.isfinite(voxel) or voxel <= 0:
            raise OctolgpError(f"Scan.downsample: voxel must be finite and > 0, got {voxel!r}")
        keys = np.floor(self.points / float(voxel)).astype(np.int64)
        if self.max_range is not None:
            length = np.linalg.norm(self.points - self.origin, axis=1)
            no_return = length >= self.max_range * (1.0 - NO_RETURN_RTOL)
            keys = np.concatenate([keys, no_return[:, None].astype(np.int64)], axis=1)
        _, first = np.unique(keys, axis=0, return_index=True)
        return Scan(
            origin=self.origin,
            points=self.points[np.sort(first)],
            max_range=self.max_range,
            stamp=self.stamp,
            rotation=self.rotation,
        )
