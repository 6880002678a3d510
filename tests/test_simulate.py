"""Simulated worlds: counts, determinism, geometry of the endpoints, ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.errors import OctolgpError
from octolgp.scan import Scan
from octolgp.sim.scenes import (
    SimulatedData,
    ray_box_distance,
    simulate_paper2d,
    simulate_room3d,
)


def _on_box_boundary(points: np.ndarray, boxes: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """True where a point lies on a face of at least one box (closure minus interior)."""
    d = points.shape[1]
    lo, hi = boxes[None, :, :d], boxes[None, :, d:]
    p = points[:, None, :]
    outside = np.maximum(np.maximum(lo - p, p - hi), 0.0).max(axis=2)  # 0 inside the closure
    depth = np.minimum(p - lo, hi - p).min(axis=2)  # 0 on a face
    return np.asarray(((outside < tol) & (np.abs(depth) < tol)).any(axis=1))


def _all_points(data: SimulatedData) -> np.ndarray:
    return np.concatenate([s.points for s in data.scans])


@pytest.fixture(scope="module")
def paper() -> SimulatedData:
    return simulate_paper2d(seed=0)


def test_paper2d_counts(paper: SimulatedData) -> None:
    assert len(paper.scans) == 28
    assert all(isinstance(s, Scan) and s.dim == 2 for s in paper.scans)
    n_beams = sum(len(s) for s in paper.scans)
    assert n_beams == 28 * 47 == 1316  # the paper reports about 1,320 observations
    assert paper.true_poses.shape == paper.noisy_poses.shape == (28, 3)
    assert paper.obstacles.shape[1] == 4
    assert paper.truth_points.shape == (9900, 2)
    assert paper.truth_labels.shape == (9900,)
    assert paper.truth_labels.dtype == np.int8
    assert set(np.unique(paper.truth_labels)) == {0, 1}


def test_paper2d_truth_grid(paper: SimulatedData) -> None:
    image = paper.truth_labels.reshape(90, 110)  # rows along y, x fastest
    xs = paper.truth_points[:110, 0]
    np.testing.assert_allclose(xs, 0.1 + 0.2 * np.arange(110))
    np.testing.assert_allclose(paper.truth_points[::110, 1], 0.1 + 0.2 * np.arange(90))
    # Outer walls are one cell thick and closed.
    assert image[0].all()
    assert image[-1].all()
    assert image[:, 0].all()
    assert image[:, -1].all()
    assert not image[1:-1, 1:-1].all()
    # Walls + L + pole: 396 + 45 + 29 + 9 occupied cells, a plausible ~5 %.
    assert int(paper.truth_labels.sum()) == 479
    assert 0.03 < paper.truth_labels.mean() < 0.1
    # Every obstacle is a union of whole 0.2 m cells.
    cells = paper.obstacles / 0.2
    np.testing.assert_allclose(cells, np.round(cells), atol=1e-9)


def test_paper2d_poses_in_free_space(paper: SimulatedData) -> None:
    for poses in (paper.true_poses, paper.noisy_poses):
        i = np.floor(poses[:, 0] / 0.2).astype(int)
        j = np.floor(poses[:, 1] / 0.2).astype(int)
        assert not paper.truth_labels.reshape(90, 110)[j, i].any()


def test_paper2d_noise_levels(paper: SimulatedData) -> None:
    err = paper.noisy_poses - paper.true_poses
    assert 0.05 < err[:, :2].std() < 0.2  # 10 cm per axis
    assert np.deg2rad(0.8) < err[:, 2].std() < np.deg2rad(4.0)  # 2 degrees
    for scan, pose in zip(paper.scans, paper.noisy_poses, strict=True):
        np.testing.assert_allclose(scan.origin, pose[:2])  # the robot believes the noisy pose
        assert scan.max_range == 30.0


def test_paper2d_every_beam_hits(paper: SimulatedData) -> None:
    lengths = np.concatenate([np.linalg.norm(s.points - s.origin, axis=1) for s in paper.scans])
    assert (lengths < 30.0).all()
    assert lengths.min() > 0.5


def test_paper2d_deterministic_by_seed() -> None:
    a, b, c = simulate_paper2d(seed=3), simulate_paper2d(seed=3), simulate_paper2d(seed=4)
    np.testing.assert_array_equal(_all_points(a), _all_points(b))
    np.testing.assert_array_equal(a.noisy_poses, b.noisy_poses)
    assert not np.array_equal(a.noisy_poses, c.noisy_poses)
    np.testing.assert_array_equal(a.truth_labels, c.truth_labels)
    np.testing.assert_array_equal(a.true_poses, c.true_poses)


def test_paper2d_noise_free_endpoints_on_obstacle_faces() -> None:
    data = simulate_paper2d(seed=0, noise=False)
    np.testing.assert_array_equal(data.noisy_poses, data.true_poses)
    points = _all_points(data)
    assert _on_box_boundary(points, data.obstacles).all()
    # The L-shaped wall and the pole are both seen.
    for box in data.obstacles[4:]:
        assert _on_box_boundary(points, box[None]).any()


def test_paper2d_rejects_bad_arguments() -> None:
    with pytest.raises(OctolgpError):
        simulate_paper2d(n_poses=1)
    with pytest.raises(OctolgpError, match="range_noise_std"):
        simulate_paper2d(range_noise_std=-1.0)


def test_ray_box_distance_simple_cases() -> None:
    box = np.array([[1.0, -1.0, 2.0, 1.0]])
    origins = np.zeros((4, 2))
    directions = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [np.sqrt(0.5), np.sqrt(0.5)]])
    t = ray_box_distance(origins, directions, box)
    np.testing.assert_allclose(t, [1.0, np.inf, np.inf, np.sqrt(2.0)])


@given(
    st.floats(-5, 5),
    st.floats(-5, 5),
    st.floats(-5, 5),
)
def test_ray_box_distance_hits_face_when_aimed_at_centre(x: float, y: float, z: float) -> None:
    box = np.array([[-1.0, -2.0, -0.5, 1.0, 2.0, 0.5]])
    origin = np.array([[x, y, z]])
    if (np.abs(origin) <= box[0, 3:] + 1e-3).all():
        return  # inside (or touching) the box: no entry
    direction = -origin / np.linalg.norm(origin)
    t = ray_box_distance(origin, direction, box)
    assert np.isfinite(t[0])
    assert _on_box_boundary(origin + t[0] * direction, box, tol=1e-9).all()


def test_room3d_counts_and_truth() -> None:
    data = simulate_room3d(seed=0)
    assert len(data.scans) == 4
    assert all(s.dim == 3 for s in data.scans)
    n_beams = sum(len(s) for s in data.scans)
    assert 500 < n_beams < 2000
    assert data.true_poses.shape == (4, 4)
    assert data.obstacles.shape[1] == 6
    assert data.truth_points.shape == (24 * 20 * 12, 3)
    assert 0.2 < data.truth_labels.mean() < 0.5  # shell of a small room + block
    coarse = simulate_room3d(seed=0, resolution=0.5)
    assert coarse.truth_points.shape == (12 * 10 * 6, 3)


def test_room3d_noise_free_endpoints_on_faces_and_deterministic() -> None:
    data = simulate_room3d(seed=1, noise=False)
    points = _all_points(data)
    assert _on_box_boundary(points, data.obstacles).all()
    assert _on_box_boundary(points, data.obstacles[-1:]).any()  # the block is seen
    again = simulate_room3d(seed=1, noise=False)
    np.testing.assert_array_equal(points, _all_points(again))
    noisy_a, noisy_b = simulate_room3d(seed=2), simulate_room3d(seed=2)
    np.testing.assert_array_equal(_all_points(noisy_a), _all_points(noisy_b))
    assert not np.array_equal(_all_points(noisy_a), points)


def test_room3d_rejects_bad_resolution() -> None:
    with pytest.raises(OctolgpError, match="resolution"):
        simulate_room3d(resolution=0.0)
