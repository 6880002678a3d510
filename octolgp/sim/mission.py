"""A long simulated 3D lidar mission, streamed lazily, for memory and long-run benchmarks.

Each scan is ray-cast analytically against the ground plane and, through a coarse
2D grid of box footprints, only the boxes within ``max_range`` of the sensor
(slab method, :func:`octolgp.sim.scenes.ray_box_distance`), so the cost of a scan
does not grow with the size of the world.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan, as_points, planar_rotation
from octolgp.sim.scenes import ray_box_distance

__all__ = ["Mission3D", "simulate_mission3d"]

SENSOR_HEIGHT = 1.0
"""Height of the lidar above the ground plane, metres."""
_CLEARANCE = 4.5  # no box comes closer than this to the route's centreline, metres
_SCAN_PERIOD = 0.1  # seconds between scans (a 10 Hz lidar)
# Unit direction of travel along each side of the counter-clockwise rectangle.
_SIDE_DIRECTIONS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])


def _side_structures(rng: np.random.Generator, side_length: float) -> FloatArray:
    """Structures lining one side, in side coordinates ``[s0, s1, l0, l1, z0, z1, inner]``.

    ``s`` runs along the side, ``l`` is the lateral offset (positive: inside the loop),
    ``inner`` is 1 for rows on the inside. Buildings (blocks 8-25 m long, set back
    7-10 m) overrun the side's ends so that the outer corners are closed.
    """
    rows, margin = [], 12.0
    for side in (1.0, -1.0):
        # Buildings in a row with gaps; half the gaps are closed by a low fence.
        n = int(np.ceil((side_length + 2 * margin) / 11.0)) + 1
        length, gap = rng.uniform(8.0, 25.0, n), rng.uniform(3.0, 10.0, n)
        start = -margin + np.cumsum(gap + length) - length
        setback, depth = rng.uniform(7.0, 10.0, n), rng.uniform(6.0, 15.0, n)
        height, fenced = rng.uniform(4.0, 15.0, n), rng.random(n) < 0.5
        keep, zero = start < side_length + margin, np.zeros(n)
        building = [start, start + length, setback, setback + depth, zero, height]
        fence = [start - gap, start, setback, setback + 0.2, zero, rng.uniform(1.0, 2.0, n)]
        here = [np.column_stack(building)[keep], np.column_stack(fence)[keep & fenced]]
        # Poles (0.2 m, 4-8 m tall) and trees (0.4 m trunk under a 2.5 x 2.5 x 2 m crown).
        m = int(np.ceil(side_length / 6.0)) + 1
        s, lat = np.cumsum(rng.uniform(6.0, 20.0, m)), rng.uniform(5.0, 6.0, m)
        tree, top = rng.random(m) < 0.5, rng.uniform(4.0, 8.0, m)
        top, half = np.where(tree, top / 2.5, top), np.where(tree, 0.2, 0.1)
        keep, zero = s < side_length, np.zeros(m)
        here.append(np.column_stack([s - half, s + half, lat - half, lat + half, zero, top])[keep])
        crown = [s - 1.25, s + 1.25, lat - 0.5, lat + 2.0, top, top + 2.0]
        here.append(np.column_stack(crown)[keep & tree])
        r = np.concatenate(here)
        if side < 0:  # mirror onto the outside of the loop
            r[:, 2:4] = -r[:, [3, 2]]
        rows.append(np.column_stack([r, np.full(len(r), side > 0)]))
    return np.concatenate(rows)


def _corners(width: float, depth: float) -> FloatArray:
    """Corners ``(4, 2)`` of the route rectangle, in driving order; side ``j`` starts at corner ``j``."""
    return np.array([[0.0, 0.0], [width, 0.0], [width, depth], [0.0, depth]])


def _ragged(counts: NDArray[np.int64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Flatten ragged rows: the row of each element and its rank within the row."""
    row = np.repeat(np.arange(counts.size), counts)
    return row, np.arange(row.size) - (np.cumsum(counts) - counts)[row]


def _build_world(rng: np.random.Generator, width: float, depth: float) -> FloatArray:
    """Boxes ``(k, 6)`` lining the counter-clockwise ``width`` x ``depth`` rectangle at the origin."""
    corners, boxes = _corners(width, depth), []
    for j, d in enumerate(_SIDE_DIRECTIONS):
        local = _side_structures(rng, width if j % 2 == 0 else depth)
        normal = np.array([-d[1], d[0]])  # left of travel: inside the loop
        c0 = corners[j] + local[:, 0:1] * d + local[:, 2:3] * normal
        c1 = corners[j] + local[:, 1:2] * d + local[:, 3:4] * normal
        lo, hi = np.minimum(c0, c1), np.maximum(c0, c1)
        # Inner rows are clipped to the interior, clear of the other three sides.
        inner = local[:, 6] > 0
        bounds = np.array([width, depth]) - _CLEARANCE
        lo[inner] = np.clip(lo[inner], _CLEARANCE, bounds)
        hi[inner] = np.clip(hi[inner], _CLEARANCE, bounds)
        ok = ((hi - lo) > 0.05).all(axis=1)
        boxes.append(np.column_stack([lo, local[:, 4:5], hi, local[:, 5:6]])[ok])
    return np.concatenate(boxes)


class Mission3D:
    """A lazily simulated lidar mission around one large closed loop, with ground truth.

    Built by :func:`simulate_mission3d`; holds only the world (a few hundred boxes per
    kilometre) and the beam pattern, never the scans.

    Attributes
    ----------
    length, spacing : float
        Route length (one lap) and distance between scans, metres.
    n_scans : int
        Number of scans, ``ceil(length / spacing)``.
    boxes : ndarray of shape (k, 6), read-only
        Obstacles ``[xmin, ymin, zmin, xmax, ymax, zmax]``, world frame, metres.
    extent : tuple of float
        ``(width, depth)`` of the route rectangle, metres; the world spans it plus
        about 30 m of buildings around.
    max_range : float
        No-return range, metres.
    """

    def __init__(
        self,
        seed: int,
        length: float,
        spacing: float,
        directions: FloatArray,
        max_range: float,
        range_noise: float,
    ) -> None:
        self.length, self.spacing, self.max_range = length, spacing, max_range
        self.n_scans = max(1, int(np.ceil(length / spacing - 1e-9)))
        self.extent = (length / 3.0, length / 6.0)
        self._seed, self._range_noise = seed, range_noise
        self._directions = directions  # (B, 3), sensor frame
        self.boxes = _build_world(np.random.default_rng([seed, 0]), *self.extent)
        self.boxes.setflags(write=False)
        # Coarse grid of box footprints: (cell key, box id) pairs sorted by key (CSR).
        self._cell = max(max_range, 10.0)
        lo = np.floor(self.boxes[:, :2] / self._cell).astype(np.int64)
        hi = np.floor(self.boxes[:, 3:5] / self._cell).astype(np.int64)
        span = hi - lo + 1
        ids, local = _ragged(span[:, 0] * span[:, 1])
        keys = self._key(lo[ids, 0] + local // span[ids, 1], lo[ids, 1] + local % span[ids, 1])
        order = np.argsort(keys, kind="stable")
        self._keys, self._ids = keys[order], ids[order]

    @staticmethod
    def _key(ix: NDArray[np.int64], iy: NDArray[np.int64]) -> NDArray[np.int64]:
        """Pack grid cell indices into one int64 key."""
        return np.asarray((ix + (1 << 30)) * (1 << 31) + (iy + (1 << 30)), dtype=np.int64)

    def route(self, s: ArrayLike) -> FloatArray:
        """Sensor pose at arc length ``s`` (metres, taken modulo the lap length).

        Returns
        -------
        ndarray of shape ``np.shape(s) + (4,)``
            ``(x, y, z, yaw)``: world frame, metres, radians CCW; ``z`` is the sensor height.
        """
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        width, depth = self.extent
        starts = np.cumsum([0.0, width, depth, width])
        side = np.searchsorted(starts, s, side="right") - 1
        along = s - starts[side]
        d = _SIDE_DIRECTIONS[side]
        xy = _corners(width, depth)[side] + along[..., None] * d
        yaw = np.arctan2(d[..., 1], d[..., 0])
        return np.concatenate([xy, np.full_like(yaw, SENSOR_HEIGHT)[..., None], yaw[..., None]], -1)

    def boxes_near(self, xy: ArrayLike) -> NDArray[np.intp]:
        """Indices of the boxes whose footprint lies within ``max_range`` of ``xy`` (metres)."""
        p = np.asarray(xy, dtype=np.float64)[:2]
        r = self.max_range
        lo = np.floor((p - r) / self._cell).astype(np.int64)
        hi = np.floor((p + r) / self._cell).astype(np.int64)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        keys = self._key(gx.ravel(), gy.ravel())
        a, b = np.searchsorted(self._keys, keys), np.searchsorted(self._keys, keys, side="right")
        ids = np.unique(np.concatenate([self._ids[i:j] for i, j in zip(a, b, strict=True)]))
        # Exact test: distance from p to the footprint rectangle.
        gap = np.maximum(np.maximum(self.boxes[ids, :2] - p, p - self.boxes[ids, 3:5]), 0.0)
        return np.asarray(ids[(gap**2).sum(axis=1) <= r * r], dtype=np.intp)

    def cast(
        self,
        origin: ArrayLike,
        yaw: float = 0.0,
        rng: np.random.Generator | None = None,
        stamp: float | None = None,
    ) -> Scan:
        """A scan of the lidar's beam pattern from ``origin`` (metres) turned by ``yaw`` (rad).

        Rays are cast against the ground plane ``z = 0`` analytically, then the nearby boxes
        (slab method). With ``rng`` the returns get Gaussian range noise of the mission's
        ``range_noise``; without, they lie exactly on the surfaces. No-returns end at exactly
        ``max_range``.
        """
        origin = np.asarray(origin, dtype=np.float64)
        c, s = np.cos(yaw), np.sin(yaw)
        u = self._directions
        dirs = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2]])
        with np.errstate(divide="ignore"):
            t = np.where(dirs[:, 2] < 0.0, -origin[2] / dirs[:, 2], np.inf)
        ids = self.boxes_near(origin)
        if ids.size:
            origins = np.broadcast_to(origin, dirs.shape)
            t = np.minimum(t, ray_box_distance(origins, dirs, self.boxes[ids]))
        hit = t < self.max_range
        if rng is not None:
            t = t + rng.normal(0.0, self._range_noise, t.shape)
        ranges = np.where(hit, np.clip(t, 0.0, self.max_range - 1e-3), self.max_range)
        points = origin + ranges[:, None] * dirs
        return Scan(origin, points, self.max_range, stamp, planar_rotation(float(yaw), 3))

    def scan(self, index: int) -> Scan:
        """Scan ``index`` in ``[0, n_scans)``, cast from ``route(index * spacing)``; else raise."""
        if not (isinstance(index, int | np.integer) and 0 <= index < self.n_scans):
            raise OctolgpError(f"Mission3D.scan: index must be in [0, {self.n_scans}), got {index}")
        x, y, z, yaw = self.route(index * self.spacing)
        rng = None
        if self._range_noise > 0:
            rng = np.random.default_rng([self._seed, 1, int(index)])
        return self.cast(np.array([x, y, z]), yaw, rng, stamp=index * _SCAN_PERIOD)

    def scans(self) -> Iterator[Scan]:
        """Yield the ``n_scans`` scans in route order, one at a time."""
        for k in range(self.n_scans):
            yield self.scan(k)

    def truth(self, points: ArrayLike) -> NDArray[np.int8]:
        """Labels ``(q,)`` int8 of ``points`` ``(q, 3)`` (world frame, metres).

        1 strictly inside a box or below the ground (``z < 0``), else 0.

        Raises
        ------
        OctolgpError
            On a wrong shape or a non-finite value.
        """
        p = as_points(points, "Mission3D.truth points", dim=3)
        out = p[:, 2] < 0.0
        cells = np.floor(p[:, :2] / self._cell).astype(np.int64)
        keys = self._key(cells[:, 0], cells[:, 1])
        a, b = np.searchsorted(self._keys, keys), np.searchsorted(self._keys, keys, side="right")
        for start in range(0, len(p), 65536):  # chunks bound the (point, box) pair arrays
            sl = slice(start, start + 65536)
            q, rank = _ragged(b[sl] - a[sl])
            q += start
            box = self.boxes[self._ids[a[q] + rank]]
            inside = ((p[q] > box[:, :3]) & (p[q] < box[:, 3:])).all(axis=1)
            out[q[inside]] = True
        return out.astype(np.int8)


def _number(
    name: str, value: object, low: float, high: float = np.inf, strict: bool = True
) -> float:
    """``value`` as a float, or raise naming ``name`` unless finite and in ``(low, high]``.

    ``strict=False`` admits ``low`` itself.
    """
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise OctolgpError(f"simulate_mission3d: {name} must be a number, got {value!r}")
    v = float(value)
    if not (np.isfinite(v) and (v > low if strict else v >= low) and v <= high):
        want = f"{'>' if strict else '>='} {low}" + (f" and <= {high}" if high < np.inf else "")
        raise OctolgpError(f"simulate_mission3d: {name} must be finite and {want}, got {value!r}")
    return v


def simulate_mission3d(
    length: float = 2000.0,
    *,
    seed: int = 0,
    spacing: float = 1.0,
    n_azimuth: int = 90,
    n_elevation: int = 8,
    fov_up: float = 15.0,
    fov_down: float = -15.0,
    max_range: float = 20.0,
    range_noise: float = 0.01,
) -> Mission3D:
    """Simulate a long 3D lidar mission along a street loop, streamed scan by scan.

    The route is ONE lap of a counter-clockwise rectangle, ``length / 3`` by
    ``length / 6`` metres (667 x 333 m for 2 km), driven once, so the explored
    area grows all mission long. Along both sides of the street stand rows of
    buildings (blocks 8-25 m long, 6-15 m deep, 4-15 m tall, set back 7-10 m from
    the centreline, gaps partly closed by 1-2 m fences), poles and trees (trunk and
    crown boxes) 5-6 m from the centreline, on a flat ground plane ``z = 0``; nothing
    comes within 4.5 m of the centreline, and the inside of a small loop is left
    empty. A spinning lidar ``SENSOR_HEIGHT`` (1 m) above the centreline casts
    ``n_azimuth`` x ``n_elevation`` beams every ``spacing`` metres.

    Parameters
    ----------
    length : float
        Route length, metres: one lap.
    seed : int
        Non-negative seed; the world and every scan's noise are functions of it.
    spacing : float
        Distance between scans along the route, metres.
    n_azimuth, n_elevation : int
        Beams over 360° of azimuth and rings between ``fov_down`` and ``fov_up``.
    fov_up, fov_down : float
        Elevation of the top and bottom rings, degrees, ``-90 <= fov_down < fov_up <= 90``.
    max_range : float
        No-return range, metres: beams hitting nothing closer end at exactly this range.
    range_noise : float
        Standard deviation of the Gaussian range noise on returns, metres, >= 0.

    Returns
    -------
    Mission3D
        ``scans()`` yields the ``ceil(length / spacing)`` scans lazily.

    Raises
    ------
    OctolgpError
        Naming the field on a non-positive or non-finite length, spacing or
        max_range, a beam count below 1, a bad field of view, negative noise or a bad seed.
    """
    length, spacing = _number("length", length, 0.0), _number("spacing", spacing, 0.0)
    max_range = _number("max_range", max_range, 0.0)
    fov = [
        _number(name, a, -90.0, 90.0, strict=False)
        for name, a in [("fov_down", fov_down), ("fov_up", fov_up)]
    ]
    range_noise = _number("range_noise", range_noise, 0.0, strict=False)
    for name, count in (("n_azimuth", n_azimuth), ("n_elevation", n_elevation)):
        if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 1:
            raise OctolgpError(f"simulate_mission3d: {name} must be an integer >= 1, got {count!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise OctolgpError(f"simulate_mission3d: seed must be an integer >= 0, got {seed!r}")
    if fov[0] >= fov[1]:
        raise OctolgpError(f"simulate_mission3d: fov_down ({fov[0]}) must be < fov_up ({fov[1]})")
    # Beam pattern in the sensor frame: azimuth over 360°, rings evenly in elevation.
    rings = (
        np.linspace(fov[0], fov[1], n_elevation) if n_elevation > 1 else np.array([sum(fov) / 2])
    )
    az, el = np.meshgrid(
        np.linspace(-np.pi, np.pi, int(n_azimuth), endpoint=False), np.deg2rad(rings), indexing="ij"
    )
    az, el = az.ravel(), el.ravel()
    directions = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Mission3D(int(seed), length, spacing, directions, max_range, range_noise)


def simulate_car_street(*, seed: int = 0, range_noise: float = 0.0) -> Mission3D:
    """The benchmarks' car-lidar street: :func:`simulate_mission3d` with a 64 x 1024 lidar.

    A 1 km lap, a scan every metre, elevations -24.9° to 2° (a 64-beam car sensor's),
    ranges to 80 m (no-returns beyond).
    """
    return simulate_mission3d(
        1000.0,
        seed=seed,
        spacing=1.0,
        n_azimuth=1024,
        n_elevation=64,
        fov_down=-24.9,
        fov_up=2.0,
        max_range=80.0,
        range_noise=range_noise,
    )
