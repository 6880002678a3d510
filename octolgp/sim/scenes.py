"""Simulated scan sequences with ground truth.

:func:`simulate_paper2d` rebuilds the 2D simulation of Kim & Kim, "Continuous
Occupancy Maps using Overlapping Local Gaussian Processes", IROS 2013 (Fig. 3):
a 22 m x 18 m walled world with an L-shaped wall and a pole, 28 poses with about
1,320 laser beams, SLAM-like pose noise, and a 0.2 m grid of test labels.
:func:`simulate_room3d` is a small 3D analogue (a box room with a block and a
3D lidar) for exercising the 3D code path.

Obstacles are axis-aligned boxes; true ranges come from a vectorised slab-method
ray/box intersection over every beam and every box at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan

__all__ = ["SimulatedData", "simulate_paper2d", "simulate_room3d"]

PAPER2D_RESOLUTION = 0.2
"""Edge of the paper's test cells and of the obstacle grid, metres."""

# Paper 2D world in 0.2 m cells: [i_min, j_min, i_max, j_max), x = 0.2 i, y = 0.2 j.
_PAPER2D_CELLS = np.array(
    [
        [0, 0, 110, 1],  # south wall
        [0, 89, 110, 90],  # north wall
        [0, 0, 1, 90],  # west wall
        [109, 0, 110, 90],  # east wall
        [30, 40, 75, 41],  # L-shaped wall: horizontal arm, y = 8.0..8.2
        [74, 41, 75, 70],  # L-shaped wall: vertical arm, x = 14.8..15.0
        [85, 20, 88, 23],  # rectangular pole, 0.6 m x 0.6 m
    ]
)
_PAPER2D_SHAPE = (110, 90)  # cells along x, y: a 22 m x 18 m world
# Robot path through the free space (world frame, metres): a U around the world
# that turns into the inside of the L.
_PAPER2D_PATH = np.array([[2, 2], [20, 2], [20, 16], [2, 16], [2, 11], [12, 11]], dtype=float)


# 3D room, metres: floor, ceiling and four walls 0.25 m thick, and a 1 m block on the floor.
_ROOM3D_SIZE = (6.0, 5.0, 3.0)
_ROOM3D_BOXES = np.array(
    [
        [0.0, 0.0, 0.0, 6.0, 5.0, 0.25],  # floor
        [0.0, 0.0, 2.75, 6.0, 5.0, 3.0],  # ceiling
        [0.0, 0.0, 0.0, 0.25, 5.0, 3.0],  # west wall
        [5.75, 0.0, 0.0, 6.0, 5.0, 3.0],  # east wall
        [0.0, 0.0, 0.0, 6.0, 0.25, 3.0],  # south wall
        [0.0, 4.75, 0.0, 6.0, 5.0, 3.0],  # north wall
        [2.5, 2.0, 0.25, 3.5, 3.0, 1.25],  # block
    ]
)


@dataclass(frozen=True, eq=False)
class SimulatedData:
    """A simulated scan sequence with its ground truth.

    Attributes
    ----------
    scans : list of Scan
        One scan per pose, expressed through the noisy (believed) pose.
    truth_points : ndarray of shape (M, d)
        Test-cell centres, world frame, metres.
    truth_labels : ndarray of shape (M,), int8
        1 where the test cell overlaps an obstacle with positive area/volume, else 0.
    true_poses, noisy_poses : ndarray of shape (P, 3) or (P, 4)
        ``(x, y, theta)`` in 2D, ``(x, y, z, yaw)`` in 3D: metres, radians CCW.
    obstacles : ndarray of shape (k, 2d)
        Axis-aligned boxes ``[min_0..min_{d-1}, max_0..max_{d-1}]``, metres;
        ``[xmin, ymin, xmax, ymax]`` in 2D.
    """

    scans: list[Scan]
    truth_points: FloatArray
    truth_labels: NDArray[np.int8]
    true_poses: FloatArray
    noisy_poses: FloatArray
    obstacles: FloatArray


def ray_box_distance(origins: FloatArray, directions: FloatArray, boxes: FloatArray) -> FloatArray:
    """Distance along each ray to the first axis-aligned box it enters (slab method).

    Parameters
    ----------
    origins : ndarray of shape (B, d)
        Ray origins, metres; outside every box.
    directions : ndarray of shape (B, d)
        Unit directions.
    boxes : ndarray of shape (k, 2d)
        ``[min..., max...]`` per box, metres.

    Returns
    -------
    ndarray of shape (B,)
        Distance to the nearest entry point (on a box face), ``inf`` where the ray
        hits nothing.
    """
    d = origins.shape[1]
    lo, hi = boxes[None, :, :d], boxes[None, :, d:]
    o, u = origins[:, None, :], directions[:, None, :]
    # Slab method: parameter interval of the ray inside each slab lo_a <= x_a <= hi_a.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t0, t1 = (lo - o) / u, (hi - o) / u
    parallel = u == 0.0
    inside = (o >= lo) & (o <= hi)
    t_lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    t_hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    # Entry = latest slab entry, exit = earliest slab exit; a hit needs entry <= exit, ahead.
    t_enter, t_exit = t_lo.max(axis=2), t_hi.min(axis=2)
    hit = (t_enter <= t_exit) & (t_enter > 0.0)
    return np.asarray(np.where(hit, t_enter, np.inf).min(axis=1), dtype=np.float64)


def _cell_labels(centres: FloatArray, resolution: float, boxes: FloatArray) -> NDArray[np.int8]:
    """1 where the cube of edge ``resolution`` around a centre overlaps a box with positive size."""
    d = centres.shape[1]
    lo, hi = boxes[None, :, :d], boxes[None, :, d:]
    c = centres[:, None, :]
    half = resolution / 2
    overlap = np.minimum(c + half, hi) - np.maximum(c - half, lo)  # (M, k, d)
    tol = 1e-6 * resolution
    occupied: NDArray[np.bool_] = np.any(np.all(overlap > tol, axis=2), axis=1)
    return occupied.astype(np.int8)


def _grid_centres(extent: tuple[float, ...], resolution: float) -> FloatArray:
    """Cell centres of a grid from the origin to ``extent``, x fastest (row-major image order)."""
    axes = [(np.arange(int(np.floor(e / resolution + 1e-9))) + 0.5) * resolution for e in extent]
    mesh = np.meshgrid(*axes[::-1], indexing="ij")[::-1]
    return np.stack([m.ravel() for m in mesh], axis=1)


def _path_poses(waypoints: FloatArray, n: int) -> FloatArray:
    """``n`` poses ``(x, y, heading)`` evenly spaced by arc length along a polyline."""
    seg = np.diff(waypoints, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.linspace(0.0, cum[-1], n)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    xy = waypoints[k] + seg[k] * ((s - cum[k]) / lengths[k])[:, None]
    return np.column_stack([xy, np.arctan2(seg[k, 1], seg[k, 0])])


def _slam_noise(
    rng: np.random.Generator,
    true_poses: FloatArray,
    ranges: FloatArray,
    max_range: float,
    stds: tuple[float, float, float] | None,
) -> tuple[FloatArray, FloatArray]:
    """Return noisy (believed) poses and noisy ranges clamped to ``[0, max_range]``.

    ``true_poses`` is ``(P, d + 1)``: position then heading. ``stds`` is
    ``(position, heading, range)`` (m, rad, m), or ``None`` for no noise. Beams
    that hit nothing within ``max_range`` are returned at exactly ``max_range``.
    """
    noisy_poses = true_poses.copy()
    if stds is not None:
        for name, value in zip(("position", "heading", "range"), stds, strict=True):
            if not (np.isfinite(value) and value >= 0):
                raise OctolgpError(f"{name}_noise_std must be finite and >= 0, got {value!r}")
        n, d = true_poses.shape[0], true_poses.shape[1] - 1
        # SLAM pose error per axis and heading, then range error per beam.
        noisy_poses[:, :d] += rng.normal(0.0, stds[0], (n, d))
        noisy_poses[:, d] += rng.normal(0.0, stds[1], n)
        ranges = ranges + rng.normal(0.0, stds[2], ranges.shape)
    ranges = np.where(ranges < max_range, np.clip(ranges, 0.0, max_range - 1e-3), max_range)
    return noisy_poses, ranges


def simulate_paper2d(
    seed: int = 0,
    *,
    noise: bool = True,
    n_poses: int = 28,
    n_beams: int = 47,
    fov: float = float(2 * np.pi),
    max_range: float = 30.0,
    position_noise_std: float = 0.1,
    heading_noise_std: float = float(np.deg2rad(2.0)),
    range_noise_std: float = 0.01,
) -> SimulatedData:
    """Simulate the 2D experiment of Kim & Kim 2013 (Fig. 3) with ground truth.

    The robot drives a path through the free space of a 22 m x 18 m world; at each
    of ``n_poses`` poses a laser with field of view ``fov`` (360° by default;
    ``pi`` gives a forward SICK-style fan) casts ``n_beams`` beams (28 x 47 = 1,316 observations
    by default). Ranges are cast from the TRUE pose, then projected
    through the NOISY pose, as a SLAM front end would believe it.

    Parameters
    ----------
    seed : int
        Seed of ``np.random.default_rng``; the output is a function of it.
    noise : bool
        ``False`` gives exact poses and ranges: every endpoint on an obstacle face.
    n_poses, n_beams : int
        Poses along the path and beams per scan.
    fov : float
        Field of view, radians, centred on the heading; ``2 * pi`` is a full circle.
    max_range : float
        No-return range, metres; beams hitting nothing (none in the closed world)
        are returned at ``max_range`` and marked no-return by ``Scan.max_range``.
    position_noise_std, heading_noise_std, range_noise_std : float
        Pose noise per axis (metres), heading noise (radians), range noise (metres).

    Returns
    -------
    SimulatedData
        Truth on the 110 x 90 grid of 0.2 m cell centres (9,900 points), x fastest.

    Raises
    ------
    OctolgpError
        On a non-positive count or range, or a negative noise level.
    """
    if n_poses < 2 or n_beams < 1 or not (np.isfinite(max_range) and max_range > 0):
        raise OctolgpError("simulate_paper2d: need n_poses >= 2, n_beams >= 1, max_range > 0")
    rng = np.random.default_rng(seed)
    obstacles = _PAPER2D_CELLS * PAPER2D_RESOLUTION
    true_poses = _path_poses(_PAPER2D_PATH, n_poses)
    if fov >= 2 * np.pi:
        angles = np.linspace(-np.pi, np.pi, n_beams, endpoint=False)
    else:  # a fan that includes both ends
        angles = np.linspace(-fov / 2.0, fov / 2.0, n_beams)

    # Ray casting from the true poses, all beams at once.
    phi = (true_poses[:, 2:3] + angles).ravel()
    origins = np.repeat(true_poses[:, :2], n_beams, axis=0)
    directions = np.column_stack([np.cos(phi), np.sin(phi)])
    ranges = ray_box_distance(origins, directions, obstacles).reshape(n_poses, n_beams)

    # Sensor noise: the robot believes the noisy pose.
    stds = (position_noise_std, heading_noise_std, range_noise_std)
    noisy_poses, ranges = _slam_noise(rng, true_poses, ranges, max_range, stds if noise else None)

    scans = [
        Scan.from_ranges(noisy_poses[k], ranges[k], angles, max_range=max_range, stamp=float(k))
        for k in range(n_poses)
    ]
    truth_points = _grid_centres((22.0, 18.0), PAPER2D_RESOLUTION)
    truth_labels = _cell_labels(truth_points, PAPER2D_RESOLUTION, obstacles)
    return SimulatedData(scans, truth_points, truth_labels, true_poses, noisy_poses, obstacles)


def simulate_room3d(
    seed: int = 0,
    n_poses: int = 4,
    *,
    resolution: float = 0.25,
    noise: bool = True,
    n_azimuth: int = 24,
    n_elevation: int = 12,
    max_range: float = 12.0,
    position_noise_std: float = 0.02,
    heading_noise_std: float = float(np.deg2rad(0.5)),
    range_noise_std: float = 0.01,
) -> SimulatedData:
    """Simulate a small 3D scene: a 6 x 5 x 3 m room with a block and a 3D lidar.

    The room's floor, ceiling and walls are 0.25 m thick boxes; a 1 x 1 x 1 m block
    stands on the floor in the middle. The lidar, 1.5 m above the floor, casts
    ``n_azimuth`` x ``n_elevation`` beams (azimuth over 360°, elevation over
    [-60°, 60°]) from ``n_poses`` poses on an ellipse around the block: 288 beams
    per pose and 1,152 in all by default.

    Parameters
    ----------
    seed, n_poses : int
        Seed of ``np.random.default_rng``; number of poses.
    resolution : float
        Edge of the ground-truth test cells, metres (0.25 gives 24 x 20 x 12 = 5,760).
    noise, n_azimuth, n_elevation, max_range, position_noise_std, heading_noise_std, range_noise_std
        As in :func:`simulate_paper2d`; azimuth x elevation is the lidar's beam grid.

    Returns
    -------
    SimulatedData
        With 3D scans, poses ``(x, y, z, yaw)`` and obstacles ``(k, 6)``.

    Raises
    ------
    OctolgpError
        On a bad count, resolution or noise level.
    """
    if n_poses < 1 or n_azimuth < 1 or n_elevation < 1 or not max_range > 0:
        raise OctolgpError("simulate_room3d: counts must be >= 1 and max_range > 0")
    if not (np.isfinite(resolution) and 0.05 <= resolution <= 3.0):
        raise OctolgpError(f"simulate_room3d: resolution must be in [0.05, 3], got {resolution!r}")
    rng = np.random.default_rng(seed)
    obstacles = _ROOM3D_BOXES
    s = np.linspace(0.0, 2 * np.pi, n_poses, endpoint=False)
    true_poses = np.column_stack(
        [3.0 + 1.6 * np.cos(s), 2.5 + 1.3 * np.sin(s), np.full(n_poses, 1.5), s + np.pi / 2]
    )
    az_grid, el_grid = np.meshgrid(
        np.linspace(-np.pi, np.pi, n_azimuth, endpoint=False),
        np.deg2rad(np.linspace(-60.0, 60.0, n_elevation)),
        indexing="ij",
    )
    az, el = az_grid.ravel(), el_grid.ravel()
    n_beams = az.size

    def beam_directions(yaw: FloatArray) -> FloatArray:
        """World-frame unit directions, shape (P * n_beams, 3), of the beams at each yaw."""
        heading = (yaw[:, None] + az).ravel()
        cos_el = np.tile(np.cos(el), yaw.size)
        return np.column_stack(
            [cos_el * np.cos(heading), cos_el * np.sin(heading), np.tile(np.sin(el), yaw.size)]
        )

    # Ray casting from the true poses, all beams at once.
    origins = np.repeat(true_poses[:, :3], n_beams, axis=0)
    ranges = ray_box_distance(origins, beam_directions(true_poses[:, 3]), obstacles)

    # Sensor noise: the robot believes the noisy pose.
    stds = (position_noise_std, heading_noise_std, range_noise_std)
    noisy_poses, ranges = _slam_noise(rng, true_poses, ranges, max_range, stds if noise else None)
    noisy_origins = np.repeat(noisy_poses[:, :3], n_beams, axis=0)
    points = noisy_origins + ranges[:, None] * beam_directions(noisy_poses[:, 3])

    chunks = np.split(points, n_poses)
    scans = [Scan(noisy_poses[k, :3], chunks[k], max_range, float(k)) for k in range(n_poses)]
    truth_points = _grid_centres(_ROOM3D_SIZE, resolution)
    truth_labels = _cell_labels(truth_points, resolution, obstacles)
    return SimulatedData(scans, truth_points, truth_labels, true_poses, noisy_poses, obstacles)
