"""Long simulated 3D mission: laziness, determinism, geometry of the returns, truth, cost."""

from __future__ import annotations

import time
import types

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.errors import OctolgpError
from octolgp.scan import Scan
from octolgp.sim.mission import SENSOR_HEIGHT, Mission3D, simulate_mission3d

MAX_RANGE = 20.0


@pytest.fixture(scope="module")
def exact() -> Mission3D:
    """A noise-free 300 m loop with a scan every 3 m."""
    return simulate_mission3d(300.0, spacing=3.0, range_noise=0.0)


def _beams(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """Length and unit direction of every beam."""
    d = scan.points - scan.origin
    r = np.linalg.norm(d, axis=1)
    return r, d / r[:, None]


def test_scans_are_lazy_and_counted() -> None:
    mission = simulate_mission3d()  # 2 km, one scan per metre
    assert mission.n_scans == 2000
    assert mission.length == 2000.0
    gen = mission.scans()
    assert isinstance(gen, types.GeneratorType)
    first = next(gen)
    assert isinstance(first, Scan)
    assert len(first) == 90 * 8
    assert first.max_range == MAX_RANGE
    assert first.stamp == 0.0
    assert simulate_mission3d(100.0, spacing=3.0).n_scans == 34  # ceil(100 / 3)
    small = simulate_mission3d(50.0, spacing=2.5, n_azimuth=8, n_elevation=2)
    scans = list(small.scans())
    assert len(scans) == small.n_scans == 20
    np.testing.assert_allclose([s.stamp for s in scans], 0.1 * np.arange(20))


def test_deterministic() -> None:
    a, b = (simulate_mission3d(150.0, seed=3, spacing=7.0) for _ in range(2))
    np.testing.assert_array_equal(a.boxes, b.boxes)
    for sa, sb in zip(a.scans(), b.scans(), strict=True):
        np.testing.assert_array_equal(sa.points, sb.points)
        np.testing.assert_array_equal(sa.origin, sb.origin)
        assert sa.stamp == sb.stamp
    # Random access gives the same scan as streaming.
    np.testing.assert_array_equal(a.scan(5).points, list(b.scans())[5].points)
    other = simulate_mission3d(150.0, seed=4, spacing=7.0)
    assert other.boxes.shape != a.boxes.shape or not np.array_equal(other.boxes, a.boxes)


def test_route_is_one_closed_lap() -> None:
    mission = simulate_mission3d(1200.0)
    width, depth = mission.extent
    assert 2 * (width + depth) == pytest.approx(1200.0)
    s = np.linspace(0.0, 1200.0, 2401)
    poses = mission.route(s)
    assert poses.shape == (2401, 4)
    np.testing.assert_allclose(poses[0], poses[-1], atol=1e-9)
    np.testing.assert_allclose(poses[:, 2], SENSOR_HEIGHT)
    steps = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.5, atol=1e-9)  # arc length, corners included
    # The sensor is always in free space.
    assert not mission.truth(poses[:, :3]).any()


def test_points_within_max_range_and_no_returns_exact(exact: Mission3D) -> None:
    n_hits = n_misses = 0
    for scan in exact.scans():
        r, _ = _beams(scan)
        assert (r <= MAX_RANGE * (1 + 1e-12)).all()
        miss = r >= MAX_RANGE * (1 - 1e-9)
        np.testing.assert_allclose(r[miss], MAX_RANGE, rtol=1e-12)
        assert (r[~miss] <= MAX_RANGE - 1e-3 + 1e-9).all()
        n_hits, n_misses = n_hits + int((~miss).sum()), n_misses + int(miss.sum())
    assert n_hits > 0
    assert n_misses > 0


def test_noisy_points_within_max_range() -> None:
    mission = simulate_mission3d(80.0, spacing=4.0, range_noise=0.5)
    for scan in mission.scans():
        r, _ = _beams(scan)
        assert (r <= MAX_RANGE * (1 + 1e-12)).all()


def test_hits_lie_on_surfaces(exact: Mission3D) -> None:
    on_surface = n_hits = n_ground = 0
    for scan in exact.scans():
        r, u = _beams(scan)
        hit = r < MAX_RANGE * (1 - 1e-9)
        p, u = scan.points[hit], u[hit]
        after, before = exact.truth(p + 0.01 * u), exact.truth(p - 0.01 * u)
        on_surface += int(((after == 1) & (before == 0)).sum())
        n_hits += int(hit.sum())
        n_ground += int((np.abs(p[:, 2]) < 1e-9).sum())
    assert on_surface >= 0.95 * n_hits
    assert 0 < n_ground < n_hits  # both the ground and the boxes are seen


def test_truth_labels(exact: Mission3D) -> None:
    boxes = exact.boxes
    centres = (boxes[:, :3] + boxes[:, 3:]) / 2
    labels = exact.truth(centres)
    assert labels.dtype == np.int8
    assert labels.shape == (len(boxes),)
    assert labels.all()
    column = np.array([[0.0, 0.0, -0.1], [0.0, 0.0, 0.1], [0.0, 0.0, 30.0]])
    assert exact.truth(column).tolist() == [1, 0, 0]  # below ground, above ground, in the sky
    assert exact.truth(np.empty((0, 3))).shape == (0,)
    with pytest.raises(OctolgpError, match="truth"):
        exact.truth(np.zeros((3, 2)))


@given(seed=st.integers(0, 2**31), length=st.floats(5.0, 3000.0))
def test_route_never_inside_a_box(seed: int, length: float) -> None:
    mission = simulate_mission3d(length, seed=seed)
    poses = mission.route(np.linspace(0.0, length, 997))
    assert not mission.truth(poses[:, :3]).any()


def test_per_scan_cost_does_not_grow() -> None:
    short = simulate_mission3d(400.0)
    long = simulate_mission3d(40_000.0)  # 13 km x 6.7 km loop, ~14,000 boxes
    assert len(long.boxes) > 20 * len(short.boxes)

    def examined(m: Mission3D, s: np.ndarray) -> int:
        return max(len(m.boxes_near(p[:2])) for p in m.route(s))

    # Boxes examined per scan: bounded by the neighbourhood, not the world.
    stretch = np.arange(0.0, 400.0, 4.0)
    early, late = examined(long, stretch), examined(long, 39_000.0 + stretch)
    assert max(early, late) <= 60
    assert max(early, late) <= 2 * examined(short, stretch) + 10

    def seconds(indices: range) -> float:
        start = time.perf_counter()
        for k in indices:
            long.scan(k)
        return time.perf_counter() - start

    seconds(range(5))  # warm up
    first, last = seconds(range(40)), seconds(range(long.n_scans - 40, long.n_scans))
    assert last < 3 * first + 0.02


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"length": 0.0}, "length"),
        ({"length": -5.0}, "length"),
        ({"length": float("inf")}, "length"),
        ({"spacing": 0.0}, "spacing"),
        ({"spacing": float("nan")}, "spacing"),
        ({"n_azimuth": 0}, "n_azimuth"),
        ({"n_elevation": 0}, "n_elevation"),
        ({"n_azimuth": 2.5}, "n_azimuth"),
        ({"max_range": 0.0}, "max_range"),
        ({"max_range": -1.0}, "max_range"),
        ({"fov_down": 15.0}, "fov_down"),
        ({"fov_down": 20.0, "fov_up": 10.0}, "fov_down"),
        ({"fov_up": float("nan")}, "fov_up"),
        ({"fov_up": 91.0}, "fov_up"),
        ({"range_noise": -0.1}, "range_noise"),
        ({"range_noise": float("inf")}, "range_noise"),
        ({"seed": -1}, "seed"),
        ({"length": "2000"}, "length"),
    ],
)
def test_bad_arguments_raise(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        simulate_mission3d(**kwargs)  # type: ignore[arg-type]


def test_bad_scan_index_raises(exact: Mission3D) -> None:
    for index in (-1, exact.n_scans):
        with pytest.raises(OctolgpError, match="index"):
            exact.scan(index)
