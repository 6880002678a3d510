"""A spinning 3D lidar in a furnished room, with exact ground truth (``tools/bench_3d.py``'s scene).

:func:`simulate_lidar_room` builds a 20 x 20 x 5 m room: floor, ceiling and four
walls 0.3 m thick, and 14 axis-aligned boxes inside (floor-to-ceiling pillars,
crates, shelving along the walls, a table, a low platform, a partition, a duct and
a lamp hanging from the ceiling). A 32 x 1024 lidar (360° of azimuth, rings from
-15° to +15°, 30 m range) mounted 1.2 m above the floor scans from poses evenly
spaced on an elliptic loop around the middle of the room (semi-axes 6 m x 5 m),
each turned by a seeded yaw offset; a few extra poses, on a loop 0.9 times the
size and half a pose spacing along from the training poses, are held out for testing.

Every return is the exact first intersection of the beam with a box (slab method,
:func:`octolgp.sim.scenes.ray_box_distance`), optionally with Gaussian range noise
(default none). :meth:`LidarRoom.truth` says whether a point lies inside a box, and
:meth:`LidarRoom.heldout_points` turns the held-out beams into labelled test points
against that geometry.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan, as_points, planar_rotation
from octolgp.sim.scenes import ray_box_distance

__all__ = ["ROOM_SIZE", "SENSOR_HEIGHT", "LidarRoom", "simulate_lidar_room"]

ROOM_SIZE = (20.0, 20.0, 5.0)
"""Inside of the room, metres: ``x`` in [0, 20], ``y`` in [0, 20], ``z`` in [0, 5]."""

SENSOR_HEIGHT = 1.2
"""Height of the lidar above the floor, metres."""

_WALL = 0.3  # thickness of floor, ceiling and walls, metres
_LOOP_CENTRE = (10.0, 10.0)
_LOOP_AXES = (6.0, 5.0)  # semi-axes of the training loop, metres
_HELDOUT_SCALE = 0.9  # held-out poses lie on the loop scaled by this about its centre
_SCAN_PERIOD = 0.1  # seconds between scans (a 10 Hz lidar)

# Boxes [xmin, ymin, zmin, xmax, ymax, zmax], metres. None comes within 1.0 m of the
# training loop or 0.6 m of the held-out loop at sensor height (checked by the tests).
_W, _X, _Y, _Z = _WALL, ROOM_SIZE[0], ROOM_SIZE[1], ROOM_SIZE[2]
_BOXES = (
    (-_W, -_W, -_W, _X + _W, _Y + _W, 0.0),  # floor
    (-_W, -_W, _Z, _X + _W, _Y + _W, _Z + _W),  # ceiling
    (-_W, -_W, 0.0, 0.0, _Y + _W, _Z),  # west wall
    (_X, -_W, 0.0, _X + _W, _Y + _W, _Z),  # east wall
    (0.0, -_W, 0.0, _X, 0.0, _Z),  # south wall
    (0.0, _Y, 0.0, _X, _Y + _W, _Z),  # north wall
    (1.7, 1.7, 0.0, 2.3, 2.3, _Z),  # pillar, south-west
    (17.7, 1.7, 0.0, 18.3, 2.3, _Z),  # pillar, south-east
    (1.7, 17.7, 0.0, 2.3, 18.3, _Z),  # pillar, north-west
    (17.7, 17.7, 0.0, 18.3, 18.3, _Z),  # pillar, north-east
    (9.75, 2.25, 0.0, 10.25, 2.75, _Z),  # pillar, south of the loop
    (9.75, 11.5, 0.0, 10.25, 12.0, _Z),  # pillar inside the loop
    (8.5, 8.5, 0.0, 11.5, 11.0, 1.0),  # table-high block in the middle
    (12.5, 7.0, 0.0, 13.3, 7.8, 0.8),  # crate inside the loop
    (14.0, 0.0, 0.0, 17.0, 1.5, 2.0),  # crates against the south wall
    (0.0, 7.0, 0.0, 1.2, 13.0, 2.2),  # shelving against the west wall
    (18.5, 8.0, 0.0, 20.0, 11.0, 1.5),  # cabinet against the east wall
    (15.5, 15.5, 0.0, 17.0, 16.5, 1.2),  # crate, north-east
    (3.0, 16.5, 4.2, 17.0, 17.2, _Z),  # duct under the ceiling
    (6.0, 5.0, 3.5, 6.6, 5.6, _Z),  # lamp hanging from the ceiling
    (4.0, 17.8, 0.0, 8.0, 18.0, 2.5),  # partition, north
    (0.0, 3.0, 0.0, 3.0, 6.0, 0.4),  # low platform, west
)


def _loop(angles: FloatArray, scale: float) -> FloatArray:
    """Points ``(n, 2)`` on the loop (scaled about its centre) at parameter ``angles``."""
    return np.column_stack(
        [
            _LOOP_CENTRE[0] + scale * _LOOP_AXES[0] * np.cos(angles),
            _LOOP_CENTRE[1] + scale * _LOOP_AXES[1] * np.sin(angles),
        ]
    )


def _poses(angles: FloatArray, scale: float, yaw_offset: FloatArray) -> FloatArray:
    """Poses ``(n, 4)`` ``(x, y, z, yaw)`` on the loop, heading along it plus ``yaw_offset``."""
    xy = _loop(angles, scale)
    tangent = np.column_stack([-_LOOP_AXES[0] * np.sin(angles), _LOOP_AXES[1] * np.cos(angles)])
    heading = np.arctan2(tangent[:, 1], tangent[:, 0])
    z = np.full(angles.size, SENSOR_HEIGHT)
    return np.column_stack([xy, z, heading + yaw_offset])


def beam_pattern(n_azimuth: int, n_elevation: int, fov_down: float, fov_up: float) -> FloatArray:
    """Unit beam directions ``(n_elevation * n_azimuth, 3)`` in the sensor frame.

    Ring-major (all azimuths of the lowest ring first); azimuth from -180° over the
    full circle, rings evenly spaced from ``fov_down`` to ``fov_up`` (degrees).
    """
    az = np.linspace(-np.pi, np.pi, n_azimuth, endpoint=False)
    el = np.deg2rad(np.linspace(fov_down, fov_up, n_elevation))
    el_grid, az_grid = np.meshgrid(el, az, indexing="ij")
    cos_el = np.cos(el_grid).ravel()
    return np.column_stack(
        [
            cos_el * np.cos(az_grid.ravel()),
            cos_el * np.sin(az_grid.ravel()),
            np.sin(el_grid.ravel()),
        ]
    )


@dataclass(frozen=True, eq=False)
class LidarRoom:
    """A room of boxes, the lidar's beam pattern and its poses; built by :func:`simulate_lidar_room`.

    Attributes
    ----------
    boxes : ndarray of shape (k, 6), read-only
        ``[xmin, ymin, zmin, xmax, ymax, zmax]`` per box, world frame, metres.
    poses, heldout_poses : ndarray of shape (n, 4), read-only
        ``(x, y, z, yaw)`` of the training and held-out scans: metres, radians CCW.
    directions : ndarray of shape (B, 3), read-only
        Unit beam directions in the sensor frame (yaw 0).
    max_range : float
        No-return range, metres: a beam that hits nothing closer ends at exactly this.
    range_noise : float
        Standard deviation of the Gaussian range noise of training returns, metres.
    seed : int
        The seed everything random derives from.
    """

    boxes: FloatArray
    poses: FloatArray
    heldout_poses: FloatArray
    directions: FloatArray
    max_range: float
    range_noise: float
    seed: int

    @property
    def n_scans(self) -> int:
        """Number of training scans."""
        return int(self.poses.shape[0])

    def world_directions(self, yaw: float) -> FloatArray:
        """Unit beam directions ``(B, 3)`` in the world frame for a sensor turned by ``yaw``."""
        c, s = np.cos(yaw), np.sin(yaw)
        u = self.directions
        return np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2]])

    def ranges(self, pose: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Exact ranges from ``pose`` ``(x, y, z, yaw)``: ``(ranges (B,), directions (B, 3))``.

        ``ranges`` is the distance to the first box face along each world-frame unit
        direction, ``inf`` where the beam hits nothing.
        """
        p = np.asarray(pose, dtype=np.float64)
        dirs = self.world_directions(float(p[3]))
        origins = np.broadcast_to(p[:3], dirs.shape)
        return ray_box_distance(origins, dirs, self.boxes), dirs

    def cast(
        self, pose: ArrayLike, rng: np.random.Generator | None = None, stamp: float | None = None
    ) -> Scan:
        """A scan from ``pose``; returns beyond ``max_range`` end at exactly ``max_range``.

        With ``rng`` the returns get Gaussian range noise of ``range_noise``.
        """
        p = np.asarray(pose, dtype=np.float64)
        t, dirs = self.ranges(p)
        hit = t < self.max_range
        if rng is not None and self.range_noise > 0:
            t = t + rng.normal(0.0, self.range_noise, t.shape)
        r = np.where(hit, np.clip(t, 0.0, self.max_range * (1.0 - 1e-6)), self.max_range)
        rotation = planar_rotation(float(p[3]), 3)  # the sensor turned by its yaw
        return Scan(p[:3], p[:3] + r[:, None] * dirs, self.max_range, stamp, rotation)

    def scan(self, index: int) -> Scan:
        """Training scan ``index`` in ``[0, n_scans)``, with the room's range noise."""
        if not (isinstance(index, int | np.integer) and 0 <= index < self.n_scans):
            raise OctolgpError(f"LidarRoom.scan: index must be in [0, {self.n_scans}), got {index}")
        rng = np.random.default_rng([self.seed, 1, int(index)])
        return self.cast(self.poses[index], rng, stamp=float(index) * _SCAN_PERIOD)

    def scans(self) -> list[Scan]:
        """All training scans, in loop order."""
        return [self.scan(i) for i in range(self.n_scans)]

    def heldout_scan(self, index: int) -> Scan:
        """Held-out scan ``index``: exact ranges, never noisy."""
        if not (isinstance(index, int | np.integer) and 0 <= index < len(self.heldout_poses)):
            raise OctolgpError(f"LidarRoom.heldout_scan: bad index {index}")
        return self.cast(self.heldout_poses[index])

    def truth(self, points: ArrayLike) -> NDArray[np.int8]:
        """Labels ``(q,)`` int8 of ``points`` ``(q, 3)``: 1 strictly inside a box, else 0.

        Raises
        ------
        OctolgpError
            On a wrong shape or a non-finite value.
        """
        p = as_points(points, "LidarRoom.truth points", dim=3)
        out = np.zeros(p.shape[0], dtype=bool)
        for start in range(0, p.shape[0], 65536):  # chunks bound the (point, box) arrays
            q = p[start : start + 65536, None, :]
            inside = np.logical_and(q > self.boxes[None, :, :3], q < self.boxes[None, :, 3:])
            out[start : start + 65536] = np.any(np.all(inside, axis=2), axis=1)
        return out.astype(np.int8)

    def heldout_points(
        self,
        *,
        voxel: float | None = 0.2,
        inside: float = 0.05,
        short: float = 0.3,
        free_per_beam: int = 1,
    ) -> tuple[FloatArray, NDArray[np.int8], int]:
        """Labelled test points from the held-out poses, against the exact geometry.

        Per held-out beam (after a voxel filter of the held-out scan at ``voxel``,
        so the test points spread evenly over the surfaces instead of crowding near
        the sensor): the hit pushed ``inside`` metres further along the beam is
        occupied, and ``free_per_beam`` points drawn uniformly along ``[0, d -
        short)`` of a beam of true range ``d`` (``[0, max_range)`` for a no-return)
        are free. Every point is then checked against :meth:`truth`; the few that
        disagree (a beam grazing a box edge leaves the box within ``inside``) are
        dropped and counted.

        Returns
        -------
        points : ndarray of shape (m, 3)
            Occupied points first, then free points.
        labels : ndarray of int8, shape (m,)
            1 occupied, 0 free.
        dropped : int
            Candidate points whose label the exact geometry contradicted.
        """
        if free_per_beam < 0 or inside < 0 or short < 0:
            raise OctolgpError("LidarRoom.heldout_points: counts and distances must be >= 0")
        rng = np.random.default_rng([self.seed, 2])
        occ, free = [], []
        for k in range(len(self.heldout_poses)):
            pose = self.heldout_poses[k]
            t, dirs = self.ranges(pose)
            if voxel is not None:
                ends = pose[:3] + np.minimum(t, self.max_range)[:, None] * dirs
                _, first = np.unique(
                    np.column_stack([np.floor(ends / voxel), t < self.max_range]),
                    axis=0,
                    return_index=True,
                )
                keep = np.sort(first)
                t, dirs = t[keep], dirs[keep]
            o, f = beam_test_points(
                pose[:3],
                t,
                dirs,
                t < self.max_range,
                self.max_range,
                rng,
                inside=inside,
                short=short,
                free_per_beam=free_per_beam,
            )
            occ.append(o)
            free.append(f)
        return true_labels(np.concatenate(occ), np.concatenate(free), self.truth)


def beam_test_points(
    origin: FloatArray,
    t: FloatArray,
    dirs: FloatArray,
    hit: NDArray[np.bool_],
    max_range: float,
    rng: np.random.Generator,
    *,
    inside: float,
    short: float,
    free_per_beam: int = 1,
) -> tuple[FloatArray, FloatArray]:
    """Candidate test points of one held-out scan: occupied behind each hit, free before it.

    Parameters
    ----------
    origin : ndarray of shape (3,)
        Sensor position, metres, world frame.
    t, dirs : ndarray of shape (b,) and (b, 3)
        Each beam's range (metres) and unit direction.
    hit : ndarray of bool, shape (b,)
        The beam returned (else it is a no-return of ``max_range``).
    max_range : float
    rng : numpy.random.Generator
    inside, short : float
        Metres a hit is pushed into the surface; metres short of the hit a free point
        may lie at most.
    free_per_beam : int
        Free points per beam, uniform on ``[0, t - short)`` (``[0, max_range)`` for a
        no-return).

    Returns
    -------
    occupied, free : ndarray of shape (h, 3) and (f, 3)
    """
    occupied = origin + (t[hit] + inside)[:, None] * dirs[hit]
    free_len = np.where(hit, t - short, max_range)
    beam = np.repeat(np.flatnonzero(free_len > 0), free_per_beam)
    s = rng.random(beam.size) * free_len[beam]
    return occupied, origin + s[:, None] * dirs[beam]


def true_labels(
    occupied: FloatArray, free: FloatArray, truth: Callable[[FloatArray], NDArray[np.int8]]
) -> tuple[FloatArray, NDArray[np.int8], int]:
    """Candidate points whose label the exact geometry confirms, labelled.

    Returns the points (occupied first), their labels (1 occupied, 0 free) and how
    many candidates ``truth`` (1 inside an obstacle, 0 outside) contradicted.
    """
    good_occ = truth(occupied) == 1
    good_free = truth(free) == 0
    points = np.concatenate([occupied[good_occ], free[good_free]])
    labels = np.concatenate(
        [np.ones(int(good_occ.sum()), np.int8), np.zeros(int(good_free.sum()), np.int8)]
    )
    return points, labels, int((~good_occ).sum() + (~good_free).sum())


def simulate_lidar_room(
    n_poses: int = 24,
    *,
    seed: int = 0,
    n_azimuth: int = 1024,
    n_elevation: int = 32,
    fov_down: float = -15.0,
    fov_up: float = 15.0,
    max_range: float = 30.0,
    range_noise: float = 0.0,
    n_heldout: int = 3,
    yaw_jitter: float = float(np.pi),
) -> LidarRoom:
    """Simulate a spinning 3D lidar driven around a furnished 20 x 20 x 5 m room.

    Parameters
    ----------
    n_poses : int
        Training poses, evenly spaced on the elliptic loop (semi-axes 6 m x 5 m about
        the room's centre, sensor 1.2 m above the floor), ``>= 1``.
    seed : int
        Seed (``>= 0``) of the yaw offsets, the range noise and the held-out free
        points; the output is a function of the arguments.
    n_azimuth, n_elevation : int
        Beams per ring over 360° and rings (a 32 x 1024 sensor by default).
    fov_down, fov_up : float
        Elevation of the lowest and highest ring, degrees, ``-90 <= fov_down < fov_up <= 90``.
    max_range : float
        No-return range, metres. The room's far corners are under 29 m away, so at
        30 m every beam returns.
    range_noise : float
        Standard deviation of Gaussian range noise on training returns, metres
        (default 0: every return lies exactly on a box face).
    n_heldout : int
        Held-out poses (``>= 0``), spread evenly on the loop scaled by 0.9 about its
        centre, shifted half a training-pose spacing along it; never noisy.
    yaw_jitter : float
        Each pose's yaw is its heading along the loop plus a seeded uniform offset in
        ``[-yaw_jitter, yaw_jitter]`` radians, so the beam pattern differs per scan.

    Returns
    -------
    LidarRoom

    Raises
    ------
    OctolgpError
        On a count below its minimum, a bad field of view, range, noise or seed.
    """
    ints = {"n_poses": (n_poses, 1), "n_azimuth": (n_azimuth, 1), "n_elevation": (n_elevation, 1)}
    ints |= {"n_heldout": (n_heldout, 0), "seed": (seed, 0)}
    for name, (value, low) in ints.items():
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise OctolgpError(
                f"simulate_lidar_room: {name} must be an integer >= {low}, got {value!r}"
            )
    if not (-90.0 <= fov_down < fov_up <= 90.0):
        raise OctolgpError(
            f"simulate_lidar_room: need -90 <= fov_down < fov_up <= 90, got {fov_down}, {fov_up}"
        )
    for name, number in (
        ("max_range", max_range),
        ("range_noise", range_noise),
        ("yaw_jitter", yaw_jitter),
    ):
        if not (np.isfinite(number) and number >= 0 and (number > 0 or name != "max_range")):
            bound = "> 0" if name == "max_range" else ">= 0"
            raise OctolgpError(
                f"simulate_lidar_room: {name} must be finite and {bound}, got {number!r}"
            )
    rng = np.random.default_rng([seed, 0])
    angles = 2 * np.pi * np.arange(n_poses) / n_poses
    poses = _poses(angles, 1.0, rng.uniform(-yaw_jitter, yaw_jitter, n_poses))
    h_angles = 2 * np.pi * (np.arange(n_heldout) + 0.5) / max(n_heldout, 1) + np.pi / max(
        n_poses, 1
    )
    heldout = _poses(h_angles, _HELDOUT_SCALE, rng.uniform(-yaw_jitter, yaw_jitter, n_heldout))
    boxes = np.array(_BOXES, dtype=np.float64)
    dirs = beam_pattern(int(n_azimuth), int(n_elevation), float(fov_down), float(fov_up))
    for arr in (boxes, poses, heldout, dirs):
        arr.setflags(write=False)
    return LidarRoom(boxes, poses, heldout, dirs, float(max_range), float(range_noise), int(seed))
