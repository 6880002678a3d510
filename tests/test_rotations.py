"""Properties of :mod:`octolgp.geometry.rotations` and agreement with scipy's conventions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from octolgp.geometry.rotations import (
    QuaternionOrder,
    axis_angle_to_matrix,
    euler_xyz_to_matrix,
    matrix_to_quaternion,
    quaternion_to_matrix,
    rpy_to_matrix,
)

ANGLE = st.floats(-4 * np.pi, 4 * np.pi, allow_nan=False)
COMPONENT = st.floats(-10.0, 10.0, allow_nan=False)
QUATERNION = arrays(np.float64, 4, elements=COMPONENT).filter(lambda q: np.linalg.norm(q) > 1e-3)
AXIS = arrays(np.float64, 3, elements=COMPONENT).filter(lambda a: np.linalg.norm(a) > 1e-3)
TOL = 1e-12


def _is_rotation(R: np.ndarray) -> None:
    assert R.shape[-2:] == (3, 3)
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), eye, atol=TOL)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=TOL)


@given(QUATERNION)
def test_quaternion_xyzw_is_scipy(q: np.ndarray) -> None:
    R = quaternion_to_matrix(q)
    _is_rotation(R)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=TOL)
    np.testing.assert_allclose(quaternion_to_matrix(-q), R, atol=TOL)


@given(QUATERNION)
def test_quaternion_wxyz_is_scalar_first(q: np.ndarray) -> None:
    R = quaternion_to_matrix(q, order="wxyz")
    _is_rotation(R)
    np.testing.assert_allclose(R, Rotation.from_quat(q, scalar_first=True).as_matrix(), atol=TOL)
    np.testing.assert_allclose(R, quaternion_to_matrix(np.roll(q, -1), order="xyzw"), atol=TOL)


@given(QUATERNION, st.sampled_from(["xyzw", "wxyz"]))
def test_matrix_to_quaternion_round_trip(q: np.ndarray, order: QuaternionOrder) -> None:
    R = quaternion_to_matrix(q, order=order)
    back = matrix_to_quaternion(R, order=order)
    np.testing.assert_allclose(np.linalg.norm(back), 1.0, atol=TOL)
    w = back[0] if order == "wxyz" else back[3]
    assert w >= 0
    unit = q / np.linalg.norm(q)
    assert np.allclose(back, unit, atol=1e-9) or np.allclose(back, -unit, atol=1e-9)
    np.testing.assert_allclose(quaternion_to_matrix(back, order=order), R, atol=TOL)


@pytest.mark.parametrize(
    "R", [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
)
def test_matrix_to_quaternion_half_turns(R: np.ndarray) -> None:
    # w = 0: every pivot but the scalar one is exercised
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=TOL)


@given(ANGLE, ANGLE, ANGLE)
def test_rpy_is_extrinsic_xyz(roll: float, pitch: float, yaw: float) -> None:
    R = rpy_to_matrix(roll, pitch, yaw)
    _is_rotation(R)
    expected = Rotation.from_euler("xyz", [roll, pitch, yaw]).as_matrix()
    np.testing.assert_allclose(R, expected, atol=TOL)
    Rx, Ry, Rz = (rpy_to_matrix(*a) for a in ((roll, 0, 0), (0, pitch, 0), (0, 0, yaw)))
    np.testing.assert_allclose(R, Rz @ Ry @ Rx, atol=TOL)


@given(arrays(np.float64, 3, elements=st.floats(-720, 720, allow_nan=False)))
def test_euler_xyz_is_intrinsic_xyz(angles: np.ndarray) -> None:
    R = euler_xyz_to_matrix(angles, degrees=True)
    _is_rotation(R)
    expected = Rotation.from_euler("XYZ", angles, degrees=True).as_matrix()
    np.testing.assert_allclose(R, expected, atol=TOL)
    assert np.array_equal(R, euler_xyz_to_matrix(np.radians(angles)))


@given(AXIS, ANGLE)
def test_axis_angle_is_rotvec(axis: np.ndarray, angle: float) -> None:
    R = axis_angle_to_matrix(axis, angle)
    _is_rotation(R)
    rotvec = angle * axis / np.linalg.norm(axis)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-11)


def test_axis_angle_zero_axis_is_identity() -> None:
    assert np.array_equal(axis_angle_to_matrix(np.zeros(3), 1.0), np.eye(3))


@settings(max_examples=25)
@given(st.integers(0, 2**32 - 1))
def test_batches_equal_one_at_a_time_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(2, 5, 4))
    angles = rng.uniform(-7, 7, size=(2, 5, 3))
    axis = rng.normal(size=(2, 5, 3))
    batch = {
        "quaternion": quaternion_to_matrix(q, order="wxyz"),
        "rpy": rpy_to_matrix(angles[..., 0], angles[..., 1], angles[..., 2]),
        "euler": euler_xyz_to_matrix(angles),
        "axis_angle": axis_angle_to_matrix(axis, angles[..., 0]),
    }
    assert {k: v.shape for k, v in batch.items()} == dict.fromkeys(batch, (2, 5, 3, 3))
    back = matrix_to_quaternion(batch["quaternion"], order="wxyz")
    for i, j in np.ndindex(2, 5):
        one = {
            "quaternion": quaternion_to_matrix(q[i, j], order="wxyz"),
            "rpy": rpy_to_matrix(*angles[i, j]),
            "euler": euler_xyz_to_matrix(angles[i, j]),
            "axis_angle": axis_angle_to_matrix(axis[i, j], angles[i, j, 0]),
        }
        for name, R in one.items():
            assert np.array_equal(batch[name][i, j], R), name
        assert np.array_equal(back[i, j], matrix_to_quaternion(one["quaternion"], order="wxyz"))


def test_invalid_quaternions_give_nan_and_bad_shapes_raise() -> None:
    assert np.isnan(quaternion_to_matrix(np.zeros(4))).all()
    assert np.isnan(quaternion_to_matrix([np.nan, 0.0, 0.0, 1.0])).all()
    with pytest.raises(ValueError, match="order"):
        quaternion_to_matrix([0.0, 0.0, 0.0, 1.0], order="zyxw")
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        quaternion_to_matrix(np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        matrix_to_quaternion(np.eye(4))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        euler_xyz_to_matrix(np.zeros(2))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        axis_angle_to_matrix(np.zeros(4), 0.0)
