"""Rotation matrices from quaternions, roll/pitch/yaw, Euler angles and axis-angle, vectorised.

Conventions, for every function here:

- A matrix ``R`` is an active rotation of column vectors: a point of the child (sensor) frame
  is ``p_parent = R @ p_child``. Arrays of rotations have shape ``(..., 3, 3)``.
- Quaternions are Hamilton quaternions (``ij = k``), ``q = w + xi + yj + zk``, as in ROS,
  Eigen, OctoMap, PCL, Rerun and scipy. ``order`` says how the four numbers are stored:
  ``"xyzw"`` (ROS messages, Rerun, scipy's default) or ``"wxyz"`` (OctoMap ``pose6d``, PCD
  ``VIEWPOINT``, Eigen's constructor). ``q`` and ``-q`` are the same rotation.
- Angles are radians unless ``degrees=True``.

Which reader uses which: ROS bags and Rerun ``Transform3D`` quaternions are ``xyzw``; OctoMap
``.graph`` poses and PCD viewpoints are ``wxyz``; OctoMap ``scan.dat`` ``NODE`` lines are
roll/pitch/yaw (:func:`rpy_to_matrix`); 3DTK ``.pose`` files are Euler angles in degrees
(:func:`euler_xyz_to_matrix`, applied to 3DTK's left-handed axes by the reader); Rerun
``RotationAxisAngle`` is :func:`axis_angle_to_matrix`.

The functions only compute: they do not validate. A zero or non-finite quaternion gives a
matrix of NaNs; readers check their input first and report it in their own terms.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from octolgp.scan import FloatArray

__all__ = [
    "QuaternionOrder",
    "axis_angle_to_matrix",
    "euler_xyz_to_matrix",
    "matrix_to_quaternion",
    "quaternion_to_matrix",
    "rpy_to_matrix",
]

QuaternionOrder = Literal["xyzw", "wxyz"]
"""How a quaternion's four numbers are stored: vector part first or scalar first."""


def _check_order(order: str) -> None:
    if order not in ("xyzw", "wxyz"):
        raise ValueError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")


def _matrices(rows: list[list[FloatArray]]) -> FloatArray:
    """Stack a 3x3 nested list of equally shaped arrays into shape ``(..., 3, 3)``."""
    out: FloatArray = np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)
    return out


def quaternion_to_matrix(q: ArrayLike, order: QuaternionOrder = "xyzw") -> FloatArray:
    """Rotation matrices of Hamilton quaternions, each normalised first.

    Parameters
    ----------
    q : array_like of shape (..., 4)
        Quaternions, any nonzero length, stored in ``order``.
    order : {"xyzw", "wxyz"}
        ``"xyzw"``: vector part first (ROS, Rerun, scipy); ``"wxyz"``: scalar first
        (OctoMap, PCD ``VIEWPOINT``).

    Returns
    -------
    ndarray of shape (..., 3, 3)
        ``R`` with ``p_parent = R @ p_child``; ``q`` and ``-q`` give the same ``R``. All NaN
        for a zero or non-finite quaternion.

    Raises
    ------
    ValueError
        If the last axis is not of length 4 or ``order`` is unknown.
    """
    _check_order(order)
    qa = np.asarray(q, dtype=np.float64)
    if qa.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have shape (..., 4), got {qa.shape}")
    norm = np.linalg.norm(qa, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = qa / norm
    if order == "xyzw":
        x, y, z, w = np.moveaxis(unit, -1, 0)
    else:
        w, x, y, z = np.moveaxis(unit, -1, 0)
    return _matrices(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: ArrayLike, order: QuaternionOrder = "xyzw") -> FloatArray:
    """Unit quaternions of rotation matrices, with a nonnegative scalar part.

    Shepperd's method: each quaternion is computed from the largest of ``4w²``, ``4x²``,
    ``4y²``, ``4z²``, so it stays accurate for every rotation, then normalised (which also
    absorbs a slightly non-orthonormal input).

    Parameters
    ----------
    R : array_like of shape (..., 3, 3)
        Rotation matrices, ``p_parent = R @ p_child``.
    order : {"xyzw", "wxyz"}
        Storage order of the result (see :func:`quaternion_to_matrix`).

    Returns
    -------
    ndarray of shape (..., 4)
        ``q`` with ``quaternion_to_matrix(q, order) ≈ R`` and ``w >= 0``.

    Raises
    ------
    ValueError
        If the last two axes are not 3 x 3 or ``order`` is unknown.
    """
    _check_order(order)
    m = np.asarray(R, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {m.shape}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    t = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    k = np.argmax(t, axis=-1)
    pivot = np.take_along_axis(t, k[..., None], axis=-1)[..., 0]
    s = 0.5 / np.sqrt(np.maximum(pivot, 1e-300))
    big = 0.25 / s
    # the four candidates (w, x, y, z), one per pivot; the pivot's own component is ``big``
    candidates = np.stack(
        [
            np.stack([big, (m21 - m12) * s, (m02 - m20) * s, (m10 - m01) * s], axis=-1),
            np.stack([(m21 - m12) * s, big, (m01 + m10) * s, (m02 + m20) * s], axis=-1),
            np.stack([(m02 - m20) * s, (m01 + m10) * s, big, (m12 + m21) * s], axis=-1),
            np.stack([(m10 - m01) * s, (m02 + m20) * s, (m12 + m21) * s, big], axis=-1),
        ],
        axis=-2,
    )
    wxyz = np.take_along_axis(candidates, k[..., None, None], axis=-2)[..., 0, :]
    wxyz = wxyz / np.linalg.norm(wxyz, axis=-1, keepdims=True)
    wxyz = np.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    out: FloatArray = wxyz if order == "wxyz" else np.roll(wxyz, -1, axis=-1)
    return out


def rpy_to_matrix(roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> FloatArray:
    """OctoMap's roll/pitch/yaw rotation, radians: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    The ``pose6d(x, y, z, roll, pitch, yaw)`` and ``octomath::Quaternion(roll, pitch, yaw)``
    convention (``octomap/src/math/Quaternion.cpp``), the same as ROS ``tf``'s
    ``setRPY``: roll about x, then pitch about the fixed y, then yaw about the fixed z
    (extrinsic x-y-z, scipy's ``Rotation.from_euler("xyz", [roll, pitch, yaw])``).

    Parameters
    ----------
    roll, pitch, yaw : array_like
        Angles in radians, broadcast together to a shape ``S``.

    Returns
    -------
    ndarray of shape S + (3, 3)
    """
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw)))
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    cy, sy = np.cos(y), np.sin(y)
    return _matrices(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_xyz_to_matrix(angles: ArrayLike, *, degrees: bool = False) -> FloatArray:
    """Intrinsic x-y'-z'' Euler angles: ``R = Rx(a) @ Ry(b) @ Rz(c)`` for ``(a, b, c)``.

    The rotation about x, then about the new y, then about the newest z (scipy's
    ``Rotation.from_euler("XYZ", angles)``). This is 3DTK's ``EulerToMatrix4`` for
    ``.pose`` files (in degrees); 3DTK applies these usual right-hand-rule matrices to its
    left-handed axes, which the 3DTK reader converts afterwards.

    Parameters
    ----------
    angles : array_like of shape (..., 3)
        ``(a, b, c)``, radians, or degrees with ``degrees=True``.
    degrees : bool
        Whether the angles are in degrees.

    Returns
    -------
    ndarray of shape (..., 3, 3)

    Raises
    ------
    ValueError
        If the last axis is not of length 3.
    """
    a = np.asarray(angles, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"Euler angles must have shape (..., 3), got {a.shape}")
    if degrees:
        a = np.radians(a)
    sx, sy, sz = np.moveaxis(np.sin(a), -1, 0)
    cx, cy, cz = np.moveaxis(np.cos(a), -1, 0)
    zero, one = np.zeros_like(sx), np.ones_like(sx)
    Rx = _matrices([[one, zero, zero], [zero, cx, -sx], [zero, sx, cx]])
    Ry = _matrices([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
    Rz = _matrices([[cz, -sz, zero], [sz, cz, zero], [zero, zero, one]])
    R: FloatArray = Rx @ Ry @ Rz
    return R


def axis_angle_to_matrix(axis: ArrayLike, angle: ArrayLike) -> FloatArray:
    """Rodrigues' formula ``R = I + sin(θ) K + (1 − cos(θ)) K²``, ``K`` the axis' cross matrix.

    Parameters
    ----------
    axis : array_like of shape (..., 3)
        Rotation axes, any length (normalised here); a zero axis gives the identity.
    angle : array_like of shape (...)
        Angles in radians, counter-clockwise about the axis (right-hand rule), broadcast
        against the axes' leading shape.

    Returns
    -------
    ndarray of shape (..., 3, 3)
        The rotations (scipy's ``Rotation.from_rotvec(angle * unit_axis)``).

    Raises
    ------
    ValueError
        If the last axis of ``axis`` is not of length 3.
    """
    ax = np.asarray(axis, dtype=np.float64)
    if ax.shape[-1:] != (3,):
        raise ValueError(f"rotation axes must have shape (..., 3), got {ax.shape}")
    theta = np.asarray(angle, dtype=np.float64)
    shape = np.broadcast_shapes(ax.shape[:-1], theta.shape)
    ax = np.broadcast_to(ax, (*shape, 3))
    theta = np.broadcast_to(theta, shape)
    norm = np.linalg.norm(ax, axis=-1, keepdims=True)
    k = np.where(norm > 0, ax / np.where(norm > 0, norm, 1.0), 0.0)
    K = np.zeros((*shape, 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    s, c = np.sin(theta)[..., None, None], np.cos(theta)[..., None, None]
    R: FloatArray = np.eye(3) + s * K + (1 - c) * (K @ K)
    return R
