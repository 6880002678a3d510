"""ROS 2 ``sensor_msgs`` messages to beams: the one decoder behind the converters and bag reader.

:meth:`Scan.from_laserscan <octolgp.scan.Scan.from_laserscan>`,
:meth:`Scan.from_pointcloud2 <octolgp.scan.Scan.from_pointcloud2>` and
:class:`~octolgp.io.rosbag.RosbagReader` build their scans from what :func:`laserscan_beams`
and :func:`pointcloud2_points` return: the sensor origin, the world-frame endpoints and the
no-return threshold. Messages are duck-typed by their field names, so the classes of ``rclpy``
(``array.array`` ranges and data), of ``rosbags`` (numpy arrays) and any look-alike serve. This
module imports no other part of octolgp but its errors, so :mod:`octolgp.scan` can use it.

- ``LaserScan``: beam ``i`` points at ``angle_min + i * angle_increment``; when ``angle_max``
  agrees with that to float32 round-off (``|(angle_max - angle_min) / (n - 1) -
  angle_increment| <= 1e-6 |angle_increment|``) the angles are interpolated from ``angle_min``
  to ``angle_max`` in float64, so the float32 increment does not accumulate over the fan. A
  reading ``r`` with ``range_min <= r < range_max`` is a hit; ``r >= range_max`` or ``+inf`` is
  a no-return, kept as a beam of length ``range_max`` with the no-return threshold
  :data:`NO_RETURN_MARGIN` below it (as for CARMEN logs); ``NaN``, ``-inf`` and ``r <
  range_min`` are dropped (REP 117).
- ``PointCloud2``: fields ``x``, ``y``, ``z`` of type FLOAT32 or FLOAT64 at any offsets and
  ``point_step`` (other fields are skipped as padding), either byte order, rows padded to
  ``row_step`` or not, organised (``height > 1``) or not, decoded with one numpy structured
  dtype. Points with a non-finite coordinate are dropped.

A malformed message raises :class:`RosMessageError` whose message starts with the offending
field's name (``angle_increment must be > 0, got 0.0``); callers add where the message came from.
"""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError

__all__ = [
    "NO_RETURN_MARGIN",
    "Beams",
    "RosMessageError",
    "laserscan_beams",
    "pointcloud2_points",
    "pose_matrix",
    "stamp_seconds",
]

FloatArray = NDArray[np.float64]
Beams = tuple[FloatArray, FloatArray, float | None]
"""``(origin (d,), points (n, d), max_range)``: a :class:`~octolgp.scan.Scan`'s fields, metres."""

NO_RETURN_MARGIN = 1e-3
"""Metres between a LaserScan's ``range_max`` and the scan's no-return threshold; the same as
:data:`octolgp.io.carmen.NO_RETURN_MARGIN`."""

_ANGLE_RTOL = 1e-6
_RIGID_ATOL = 1e-6  # |R^T R - I| and |bottom row - (0, ..., 1)| allowed in a pose matrix
_FLOAT_FIELDS = MappingProxyType({7: "f4", 8: "f8"})  # PointField.FLOAT32, FLOAT64


class RosMessageError(OctolgpError):
    """A malformed ROS message; the message names the field."""


def _get(msg: Any, name: str) -> Any:
    """``msg.name``, or :class:`RosMessageError` naming the missing field."""
    try:
        return getattr(msg, name)
    except AttributeError:
        raise RosMessageError(f"{name}: missing (not a ROS message of this type?)") from None


def _number(msg: Any, name: str, kind: type[int] | type[float] = float) -> Any:
    """A numeric field as ``kind``, or :class:`RosMessageError` naming it."""
    value = _get(msg, name)
    try:
        return kind(value)
    except (TypeError, ValueError, OverflowError):
        raise RosMessageError(f"{name} must be a number, got {value!r}") from None


def _bytes(msg: Any, name: str) -> np.ndarray[Any, np.dtype[np.uint8]]:
    """A ``uint8[]`` field (bytes, ``array.array``, numpy array or list) as a uint8 array."""
    value = _get(msg, name)
    try:
        view: memoryview | None = memoryview(value)
    except TypeError:
        view = None
    if view is not None and view.format in ("B", "b", "c") and view.ndim == 1 and view.contiguous:
        return np.frombuffer(view, dtype=np.uint8)
    try:
        out = np.asarray(value)
    except Exception:
        raise RosMessageError(f"{name} is not a byte sequence") from None
    if out.ndim != 1 or (out.size and out.dtype.kind not in "iu"):
        raise RosMessageError(f"{name} is not a byte sequence")
    if out.size and (out.min() < 0 or out.max() > 255):
        raise RosMessageError(f"{name} holds values outside 0..255")
    return out.astype(np.uint8)


def stamp_seconds(msg: Any) -> float | None:
    """``msg.header.stamp`` in seconds (``sec + nanosec * 1e-9``), ``None`` if absent or zero."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    try:
        sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    except (AttributeError, TypeError, ValueError):
        raise RosMessageError("header.stamp must have integer sec and nanosec") from None
    if sec == 0 and nanosec == 0:
        return None
    return sec + nanosec * 1e-9


def pose_matrix(pose: ArrayLike, name: str = "pose") -> FloatArray:
    """Validate a sensor pose: ``(x, y, theta)`` or a rigid ``(3, 3)`` / ``(4, 4)`` matrix.

    Parameters
    ----------
    pose : array_like of shape (3,), (3, 3) or (4, 4)
        ``(x, y, theta)`` (metres, radians CCW) or a homogeneous sensor-to-world transform.
    name : str
        Used in error messages.

    Returns
    -------
    ndarray of shape (3,), (3, 3) or (4, 4)
        The pose as float64, shaped as given.

    Raises
    ------
    OctolgpError
        On another shape, a NaN or inf, or a matrix that is not a rigid transform (rotation
        block orthonormal with determinant +1, bottom row ``(0, ..., 0, 1)``, to 1e-6).
    """
    try:
        p = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise OctolgpError(f"{name} must be numbers, got {pose!r}") from None
    if p.shape not in ((3,), (3, 3), (4, 4)):
        raise OctolgpError(
            f"{name} must be (x, y, theta) or a 3x3 / 4x4 homogeneous matrix, got shape {p.shape}"
        )
    if not np.isfinite(p).all():
        raise OctolgpError(f"{name} contains NaN or inf")
    if p.ndim == 2:
        d = p.shape[0] - 1
        R = p[:d, :d]
        bottom = np.zeros(d + 1)
        bottom[d] = 1.0
        rigid = (
            np.abs(R.T @ R - np.eye(d)).max() <= _RIGID_ATOL
            and np.linalg.det(R) > 0
            and np.abs(p[d] - bottom).max() <= _RIGID_ATOL
        )
        if not rigid:
            raise OctolgpError(
                f"{name} is not a rigid transform (rotation block orthonormal with det +1, "
                f"bottom row 0 ... 0 1)"
            )
    return p


def _laser_angles(msg: Any, n: int) -> FloatArray:
    """Beam angles of a LaserScan, radians, shape (n,); see the module docstring."""
    a0: float = _number(msg, "angle_min")
    a1: float = _number(msg, "angle_max") if hasattr(msg, "angle_max") else math.nan
    inc: float = _number(msg, "angle_increment")
    if not (math.isfinite(a0) and math.isfinite(inc)) or (
        hasattr(msg, "angle_max") and not math.isfinite(a1)
    ):
        raise RosMessageError("NaN or inf in angle_min/angle_max/angle_increment")
    if inc <= 0:
        raise RosMessageError(f"angle_increment must be > 0, got {inc!r}")
    if n > 1 and math.isfinite(a1) and abs((a1 - a0) / (n - 1) - inc) <= _ANGLE_RTOL * inc:
        angles: FloatArray = np.linspace(a0, a1, n)
        return angles
    return a0 + inc * np.arange(n, dtype=np.float64)


def _decode_laser(msg: Any, limit: float | None) -> tuple[FloatArray, FloatArray, float]:
    """Ranges (no-returns set to the range limit), their angles, and that limit."""
    raw = _get(msg, "ranges")
    try:
        ranges = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise RosMessageError("ranges must be a sequence of numbers") from None
    if ranges.ndim != 1:
        raise RosMessageError(f"ranges must be 1D, got shape {ranges.shape}")
    angles = _laser_angles(msg, ranges.shape[0])
    rmin, rmax = _number(msg, "range_min"), _number(msg, "range_max")
    if not (math.isfinite(rmin) and math.isfinite(rmax) and 0 <= rmin < rmax):
        raise RosMessageError(
            f"range_min/range_max: need finite 0 <= range_min < range_max, got {rmin!r}, {rmax!r}"
        )
    if limit is not None:
        rmax = min(rmax, limit)
    with np.errstate(invalid="ignore"):
        no_return = ranges >= rmax  # includes +inf
        keep = no_return | (ranges >= rmin)  # excludes NaN, -inf and short readings
    out = np.where(no_return, rmax, ranges)
    return out[keep], angles[keep], rmax


def laserscan_beams(msg: Any, pose: ArrayLike, *, max_range: float | None = None) -> Beams | None:
    """A LaserScan's beams in the world frame, or ``None`` when no beam is left.

    Parameters
    ----------
    msg : sensor_msgs/msg/LaserScan
        Any object with ``angle_min``, ``angle_increment``, ``ranges``, ``range_min`` and
        ``range_max`` (``angle_max`` optional).
    pose : array_like
        The laser's world pose: ``(x, y, theta)`` or a 3x3 matrix (2D beams), or a 4x4
        matrix (3D beams in the laser's xy plane).
    max_range : float, optional
        Metres; the no-return threshold used instead of ``range_max`` when smaller.

    Returns
    -------
    Beams or None
        The origin ``(d,)``, the endpoints ``(n, d)`` and the no-return threshold
        (``range_max`` less :data:`NO_RETURN_MARGIN`).

    Raises
    ------
    RosMessageError
        On a malformed message (the field is named).
    OctolgpError
        On a bad pose.
    """
    p = pose_matrix(pose)
    ranges, angles, limit = _decode_laser(msg, max_range)
    if ranges.size == 0:
        return None
    threshold = limit - NO_RETURN_MARGIN if limit > NO_RETURN_MARGIN else None
    if p.shape == (3, 3):
        p = np.array([p[0, 2], p[1, 2], math.atan2(p[1, 0], p[0, 0])])
    if p.shape == (3,):  # as Scan.from_ranges
        phi = p[2] + angles
        points = p[:2] + ranges[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        return p[:2].copy(), points, threshold
    local = np.stack([ranges * np.cos(angles), ranges * np.sin(angles), np.zeros_like(ranges)], 1)
    return p[:3, 3].copy(), local @ p[:3, :3].T + p[:3, 3], threshold


def _cloud_dtype(msg: Any, step: int) -> np.dtype[Any]:
    """Structured dtype of one point's x, y, z fields."""
    try:
        items = list(_get(msg, "fields"))
    except TypeError:
        raise RosMessageError("fields must be a sequence of PointField") from None
    fields: dict[str, Any] = {}
    for f in items:
        fields.setdefault(str(_get(f, "name")), f)
    missing = [name for name in "xyz" if name not in fields]
    if missing:
        names = ", ".join(repr(name) for name in fields) or "none"
        raise RosMessageError(f"no {'/'.join(missing)} field (fields: {names})")
    order = ">" if _get(msg, "is_bigendian") else "<"
    formats, offsets = [], []
    for name in "xyz":
        f = fields[name]
        datatype = _number(f, "datatype", int)
        kind = _FLOAT_FIELDS.get(datatype)
        if kind is None:
            raise RosMessageError(f"field {name!r} has datatype {datatype}, not FLOAT32/64")
        if hasattr(f, "count") and _number(f, "count", int) < 1:
            raise RosMessageError(f"field {name!r} has count {f.count}, not >= 1")
        offset = _number(f, "offset", int)
        if offset < 0 or offset + int(kind[1]) > step:
            raise RosMessageError(f"field {name!r} at offset {offset} overruns point_step {step}")
        formats.append(order + kind)
        offsets.append(offset)
    return np.dtype(
        {"names": list("xyz"), "formats": formats, "offsets": offsets, "itemsize": step}
    )


def _decode_cloud(msg: Any) -> FloatArray:
    """Finite points of a PointCloud2, in its frame, shape (n, 3), metres."""
    width, height = _number(msg, "width", int), _number(msg, "height", int)
    step = _number(msg, "point_step", int)
    if step <= 0:
        raise RosMessageError(f"point_step must be > 0, got {step}")
    if width < 0 or height < 0:
        raise RosMessageError(f"width/height must be >= 0, got {width}, {height}")
    dtype = _cloud_dtype(msg, step)
    data = _bytes(msg, "data")
    row = width * step
    if data.size == height * row:
        rows = data
    elif row_step := _number(msg, "row_step", int):
        if row_step < row or data.size != height * row_step:
            raise RosMessageError(
                f"data has {data.size} bytes, width*height*point_step = {height * row}, "
                f"height*row_step = {height * row_step}"
            )
        rows = np.ascontiguousarray(data.reshape(height, row_step)[:, :row]).reshape(-1)
    else:
        raise RosMessageError(
            f"data has {data.size} bytes, width*height*point_step = {height * row}"
        )
    points = np.frombuffer(rows, dtype=dtype)
    with np.errstate(invalid="ignore"):  # a signalling NaN; dropped as NaN below
        xyz = np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def pointcloud2_points(
    msg: Any, pose: ArrayLike, *, max_range: float | None = None
) -> Beams | None:
    """A PointCloud2's finite points in the world frame, or ``None`` when none is left.

    Parameters
    ----------
    msg : sensor_msgs/msg/PointCloud2
        Any object with ``fields`` (each with ``name``, ``offset``, ``datatype``, ``count``),
        ``point_step``, ``row_step``, ``data``, ``is_bigendian``, ``height`` and ``width``.
    pose : array_like
        The sensor's world pose: a 4x4 matrix, or ``(x, y, theta)`` (the sensor at z = 0,
        turned by ``theta`` about z).
    max_range : float, optional
        Metres; returned as the no-return threshold (points this far away are no-returns).

    Returns
    -------
    Beams or None
        The origin ``(3,)``, the points ``(n, 3)`` and ``max_range``.

    Raises
    ------
    RosMessageError
        On a malformed message (the field is named).
    OctolgpError
        On a bad pose (a 3x3 matrix, which would make a 2D scan of a 3D cloud, included).
    """
    p = pose_matrix(pose)
    if p.shape == (3, 3):
        raise OctolgpError("pose: a PointCloud2 needs a 4x4 matrix or (x, y, theta), got 3x3")
    if p.shape == (3,):
        c, s = math.cos(p[2]), math.sin(p[2])
        p = np.array([[c, -s, 0, p[0]], [s, c, 0, p[1]], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    xyz = _decode_cloud(msg)
    if xyz.shape[0] == 0:
        return None
    return p[:3, 3].copy(), xyz @ p[:3, :3].T + p[:3, 3], max_range
