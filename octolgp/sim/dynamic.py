"""A changing world with exact geometry: objects that move, doors that open, people.

Two scenes of axis-aligned boxes seen by a robot driving a loop:

- :func:`simulate_dynamic_office`, 2D: a 10 x 8 m office (walls 0.2 m thick, a shelf,
  a desk, a table, a cabinet and a column) with a corridor behind a door in its east
  wall. A 0.8 m crate stands at A, then moves to B; the door (a 0.1 m thick box in a
  0.9 m wall gap) is closed, then opens; two people (0.4 m boxes) walk across the room
  at 0.6 m per scan, one west to east, one north to south. The robot drives an
  elliptic loop around the middle of the room with a 360° laser of 180 beams and
  8 m range; a beam that hits nothing within 8 m is a no-return (``Scan.max_range``).
- :func:`simulate_dynamic_room3d`, 3D: an 8 x 6 x 3 m room (floor, ceiling, walls, a
  cabinet, a table, a pillar) with a 1 m cube that moves from A to B, seen by a
  16 x 360 lidar (rings -25°..+15°) 0.8 m above the floor, each scan through
  :meth:`Scan.downsample` at 0.2 m.

Every box face lies on the centres of the voxels of the scene's resolution (0.1 m in
2D, 0.2 m in 3D: the layouts are shifted by half a voxel, :data:`SHIFT_2D`,
:data:`SHIFT_3D`), so a return on a face falls in the voxel that straddles the face,
from whichever side the beam comes, rather than on one side or the other by rounding;
such a voxel is half inside the box. Ranges are exact (no noise): the first
box face along each beam (slab method, :func:`octolgp.sim.scenes.ray_box_distance`).

:class:`DynamicScene` gives, per scan, the boxes present (static and moving), which box
each return hit, and helpers for the ground truth a benchmark needs: the voxels a box
covers (:func:`footprint_voxels`) and the voxels a scan sees free
(:meth:`DynamicScene.free_voxels`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan, as_points
from octolgp.sim.lidar3d import beam_pattern
from octolgp.sim.scenes import ray_box_distance

__all__ = [
    "NO_RETURN",
    "STATIC",
    "DynamicObject",
    "DynamicScene",
    "footprint_voxels",
    "simulate_dynamic_office",
    "simulate_dynamic_room3d",
    "voxel_keys",
]

IntArray = NDArray[np.int64]

STATIC = -1
"""Owner of a return on a static box (:meth:`DynamicScene.cast`)."""

NO_RETURN = -2
"""Owner of a beam that hit nothing within ``max_range``."""

SHIFT_2D = 0.05
"""The 2D office's layout (multiples of 0.1 m) is shifted by this on both axes, so that its
box faces lie on the centres of 0.1 m voxels."""

SHIFT_3D = 0.1
"""The 3D room's layout (multiples of 0.2 m) is shifted by this on every axis, so that its
box faces lie on the centres of 0.2 m voxels."""

ROBOT_CLEARANCE = 0.2
"""Least distance (metres) from the sensor to any box present, checked per scan."""


def _frozen(a: ArrayLike) -> FloatArray:
    """A read-only float64 copy."""
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class DynamicObject:
    """An axis-aligned box that appears, moves and disappears over a scan sequence.

    Attributes
    ----------
    name : str
        Label used by benchmarks (``"crate"``, ``"door"``, ``"person 1"``, ...).
    kind : str
        ``"box"`` (moved once), ``"door"`` (present, then gone: open), ``"person"``
        (a new position every scan while crossing), ``"cube"`` (3D).
    boxes : ndarray of shape (n_scans, 2d), read-only
        Where the object is during each scan, ``[min..., max...]`` metres; a row of
        NaN where it is absent.
    """

    name: str
    kind: str
    boxes: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "boxes", _frozen(self.boxes))

    def present(self, scan: int) -> bool:
        """Whether the object is in the world during scan ``scan``."""
        return bool(np.isfinite(self.boxes[scan]).all())

    def box_at(self, scan: int) -> FloatArray | None:
        """Its box ``(2d,)`` during scan ``scan``, ``None`` where absent."""
        return self.boxes[scan] if self.present(scan) else None

    @property
    def stints(self) -> list[tuple[int, int, FloatArray]]:
        """Runs of scans at one position: ``(first scan, end scan (exclusive), box)``."""
        out: list[tuple[int, int, FloatArray]] = []
        n = self.boxes.shape[0]
        i = 0
        while i < n:
            if not self.present(i):
                i += 1
                continue
            j = i + 1
            while j < n and self.present(j) and np.array_equal(self.boxes[j], self.boxes[i]):
                j += 1
            out.append((i, j, self.boxes[i]))
            i = j
        return out


@dataclass(frozen=True, eq=False)
class DynamicScene:
    """A world of static and moving boxes, a sensor's beam pattern and its poses.

    Built by :func:`simulate_dynamic_office` and :func:`simulate_dynamic_room3d`.

    Attributes
    ----------
    name : str
        A short description, for reports.
    static_boxes : ndarray of shape (k, 2d), read-only
        ``[min..., max...]`` per static box (walls, furniture), metres.
    objects : tuple of DynamicObject
        The things that move; none overlaps a static box or another object.
    poses : ndarray of shape (n_scans, 3) or (n_scans, 4), read-only
        Sensor pose per scan: ``(x, y, heading)`` in 2D, ``(x, y, z, yaw)`` in 3D.
    directions : ndarray of shape (B, d), read-only
        Unit beam directions in the sensor frame (heading 0).
    max_range : float
        No-return range, metres: a beam that hits nothing closer ends at exactly this.
    voxel_filter : float or None
        Edge (metres) of the voxel-grid filter each scan goes through
        (:meth:`Scan.downsample`); ``None``: every beam is kept.
    extent : ndarray of shape (2, d), read-only
        Lower and upper corner of the space worth testing (the room, its walls and
        the corridor), metres.
    scan_period : float
        Seconds between scans (the scans' stamps).
    """

    name: str
    static_boxes: FloatArray
    objects: tuple[DynamicObject, ...]
    poses: FloatArray
    directions: FloatArray
    max_range: float
    voxel_filter: float | None
    extent: FloatArray
    scan_period: float = 0.5
    _cache: dict[int, tuple[Scan, IntArray]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        for name in ("static_boxes", "poses", "directions", "extent"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        d = self.dim
        if self.static_boxes.shape[1:] != (2 * d,) or self.directions.shape[1:] != (d,):
            raise OctolgpError("DynamicScene: boxes must be (k, 2d) and directions (B, d)")
        for obj in self.objects:
            if obj.boxes.shape != (self.n_scans, 2 * d):
                raise OctolgpError(
                    f"DynamicScene: object {obj.name!r} has boxes {obj.boxes.shape}, "
                    f"expected ({self.n_scans}, {2 * d})"
                )
        for i in range(self.n_scans):  # the sensor is never inside (or against) a box
            boxes, _ = self.boxes_at(i)
            lo, hi = boxes[:, :d] - ROBOT_CLEARANCE, boxes[:, d:] + ROBOT_CLEARANCE
            o = self.poses[i, :d]
            if np.any(np.all((o > lo) & (o < hi), axis=1)):
                raise OctolgpError(f"DynamicScene: the sensor at scan {i} is within a box")

    @property
    def dim(self) -> int:
        """Spatial dimension, 2 or 3."""
        return int(self.directions.shape[1])

    @property
    def n_scans(self) -> int:
        """Number of scans."""
        return int(self.poses.shape[0])

    def boxes_at(self, scan: int) -> tuple[FloatArray, IntArray]:
        """The boxes present during scan ``scan`` and their owners.

        Returns
        -------
        boxes : ndarray of shape (m, 2d)
            Static boxes first, then each present object's box.
        owners : ndarray of int64, shape (m,)
            :data:`STATIC` for a static box, else the object's index in :attr:`objects`.
        """
        if not (isinstance(scan, int | np.integer) and 0 <= scan < self.n_scans):
            raise OctolgpError(f"DynamicScene: scan must be in [0, {self.n_scans}), got {scan!r}")
        boxes = [self.static_boxes]
        owners = [np.full(self.static_boxes.shape[0], STATIC, dtype=np.int64)]
        for j, obj in enumerate(self.objects):
            box = obj.box_at(int(scan))
            if box is not None:
                boxes.append(box[None, :])
                owners.append(np.array([j], dtype=np.int64))
        return np.concatenate(boxes), np.concatenate(owners)

    def world_directions(self, scan: int) -> FloatArray:
        """Unit beam directions ``(B, d)`` in the world frame at scan ``scan``."""
        yaw = float(self.poses[scan, self.dim])
        c, s = np.cos(yaw), np.sin(yaw)
        u = self.directions
        rotated = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1]])
        return rotated if self.dim == 2 else np.column_stack([rotated, u[:, 2]])

    def cast(self, scan: int) -> tuple[Scan, IntArray]:
        """Scan ``scan`` (voxel-filtered when :attr:`voxel_filter` is set) and what each beam hit.

        Returns
        -------
        scan : Scan
            Origin, endpoints (no-returns at exactly ``max_range``), ``max_range`` and
            stamp ``scan * scan_period``. With :attr:`voxel_filter` the points are the
            ones :meth:`Scan.downsample` keeps, in the same order.
        owners : ndarray of int64, shape (len(scan),)
            Per endpoint: :data:`STATIC`, the index of the object it hit, or
            :data:`NO_RETURN`.
        """
        if scan in self._cache:
            return self._cache[scan]
        boxes, box_owner = self.boxes_at(scan)
        d = self.dim
        dirs = self.world_directions(scan)
        origin = self.poses[scan, :d]
        origins = np.broadcast_to(origin, dirs.shape)
        per_box = np.stack([ray_box_distance(origins, dirs, b[None, :]) for b in boxes])
        first = np.argmin(per_box, axis=0)
        t = per_box[first, np.arange(dirs.shape[0])]
        hit = t < self.max_range
        owners = np.where(hit, box_owner[first], NO_RETURN).astype(np.int64)
        points = origin + np.where(hit, t, self.max_range)[:, None] * dirs
        if self.voxel_filter is not None:  # Scan.downsample's choice, keeping the owners
            keys = np.floor(points / self.voxel_filter).astype(np.int64)
            keys = np.column_stack([keys, (~hit).astype(np.int64)])
            _, keep = np.unique(keys, axis=0, return_index=True)
            keep = np.sort(keep)
            points, owners = points[keep], owners[keep]
        out = (Scan(origin, points, self.max_range, stamp=scan * self.scan_period), owners)
        self._cache[scan] = out
        return out

    def scan(self, scan: int) -> Scan:
        """Scan ``scan`` alone (see :meth:`cast`)."""
        return self.cast(scan)[0]

    def scans(self) -> list[Scan]:
        """Every scan, in order."""
        return [self.scan(i) for i in range(self.n_scans)]

    def occupied(
        self, points: ArrayLike, scan: int, *, static_only: bool = False
    ) -> NDArray[np.bool_]:
        """Whether each point ``(q, d)`` lies strictly inside a box present at scan ``scan``."""
        p = as_points(points, "DynamicScene.occupied points", dim=self.dim)
        boxes = self.static_boxes if static_only else self.boxes_at(scan)[0]
        d = self.dim
        inside = (p[:, None, :] > boxes[None, :, :d]) & (p[:, None, :] < boxes[None, :, d:])
        out: NDArray[np.bool_] = np.any(np.all(inside, axis=2), axis=1)
        return out

    def free_voxels(
        self,
        scan: int,
        resolution: float,
        margin: float | None = None,
        no_returns: bool = True,
    ) -> IntArray:
        """Voxels scan ``scan`` sees free: its beams' free parts, sampled every quarter voxel.

        A beam's free part runs from the origin to ``margin`` short of its return (to
        ``max_range`` for a no-return): the ground truth of "this scan looked through
        the voxel", independent of any map. ``no_returns=False`` leaves no-return beams
        out (octolgp's forgetting counts only beams with a return, farther than
        ``OnlineConfig.clear_margin`` from it).

        Parameters
        ----------
        scan : int
        resolution : float
            Voxel edge, metres.
        margin : float, optional
            Metres the free part stops short of a return; default one ``resolution``
            (octolgp's ``TrainingConfig.free_margin`` default).

        Returns
        -------
        ndarray of int64, shape (n, d)
            Unique voxel indices ``floor(x / resolution)``, lexicographically sorted.
        """
        s, owners = self.cast(scan)
        m = resolution if margin is None else margin
        delta = s.points - s.origin
        length = np.linalg.norm(delta, axis=1)
        free_len = np.where(owners == NO_RETURN, length, np.maximum(length - m, 0.0))
        if not no_returns:
            free_len = np.where(owners == NO_RETURN, -1.0, free_len)
        unit = delta / np.maximum(length, 1e-300)[:, None]
        step = resolution / 4.0
        counts = np.where(free_len < 0, 0, np.floor(free_len / step).astype(np.int64) + 1)
        beam = np.repeat(np.arange(length.size), counts)
        starts = np.cumsum(counts) - counts
        along = (np.arange(beam.size) - starts[beam]) * step
        along = np.minimum(along, free_len[beam])
        samples = s.origin + along[:, None] * unit[beam]
        return np.unique(voxel_keys(samples, resolution), axis=0)


def voxel_keys(points: ArrayLike, resolution: float) -> IntArray:
    """Integer voxel indices ``floor(x / resolution)`` of points ``(q, d)``."""
    p = np.asarray(points, dtype=np.float64)
    out: IntArray = np.floor(p / resolution).astype(np.int64)
    return out


def footprint_voxels(box: ArrayLike, resolution: float) -> IntArray:
    """Voxels (indices ``floor(x / resolution)``) a box overlaps with positive size.

    Parameters
    ----------
    box : array_like of shape (2d,)
        ``[min..., max...]``, metres.
    resolution : float
        Voxel edge, metres.

    Returns
    -------
    ndarray of int64, shape (n, d)
        Lexicographically sorted; their centres are ``(keys + 0.5) * resolution``.
    """
    b = np.asarray(box, dtype=np.float64)
    d = b.size // 2
    tol = 1e-9 * resolution
    lo = np.floor((b[:d] + tol) / resolution).astype(np.int64)
    hi = np.ceil((b[d:] - tol) / resolution).astype(np.int64)  # exclusive
    axes = [np.arange(lo[a], hi[a]) for a in range(d)]
    grid = np.meshgrid(*axes, indexing="ij")
    return np.column_stack([g.ravel() for g in grid])


# ----------------------------------------------------------------------------- scenes
def _loop_poses(
    n: int, per_lap: int, centre: tuple[float, float], axes: tuple[float, float]
) -> FloatArray:
    """``(n, 3)`` poses ``(x, y, heading)`` counter-clockwise on an ellipse, ``per_lap`` a lap."""
    s = 2 * np.pi * np.arange(n) / per_lap
    x = centre[0] + axes[0] * np.cos(s)
    y = centre[1] + axes[1] * np.sin(s)
    heading = np.arctan2(axes[1] * np.cos(s), -axes[0] * np.sin(s))
    return np.column_stack([x, y, heading])


def _walk(
    n_scans: int, start_scan: int, a: tuple[float, float], b: tuple[float, float], step: float
) -> FloatArray:
    """Boxes ``(n_scans, 4)`` of a 0.4 m person walking from ``a`` to ``b``, ``step`` m a scan."""
    a_, b_ = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    length = float(np.linalg.norm(b_ - a_))
    n_steps = int(np.ceil(length / step)) + 1  # the last step ends at b
    out = np.full((n_scans, 4), np.nan)
    for k in range(n_steps):
        if start_scan + k >= n_scans:
            break
        c = a_ + (b_ - a_) * min(1.0, k * step / length)
        out[start_scan + k] = [c[0] - 0.2, c[1] - 0.2, c[0] + 0.2, c[1] + 0.2]
    return out


def _schedule(n_scans: int, segments: list[tuple[int, int, list[float]]]) -> FloatArray:
    """Boxes ``(n_scans, 2d)``: each ``(first, end, box)`` segment, NaN elsewhere."""
    width = len(segments[0][2])
    out = np.full((n_scans, width), np.nan)
    for first, end, box in segments:
        out[max(first, 0) : max(min(end, n_scans), 0)] = box
    return out


def _check_int(name: str, value: object, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise OctolgpError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


# 2D office, metres before SHIFT_2D (every coordinate a multiple of 0.1 m): interior x in
# [0, 10], y in [0, 8]; walls 0.2 m thick; a door gap y in [3.0, 3.9] in the east wall, a
# corridor x in [10.2, 12.2] behind it.
_OFFICE_STATIC = (
    (-0.2, -0.2, 10.2, 0.0),  # south wall
    (-0.2, 8.0, 10.2, 8.2),  # north wall
    (-0.2, 0.0, 0.0, 8.0),  # west wall
    (10.0, -0.2, 10.2, 3.0),  # east wall, south of the door
    (10.0, 3.9, 10.2, 8.2),  # east wall, north of the door
    (12.2, -0.2, 12.4, 8.2),  # far wall of the corridor
    (0.0, 2.0, 0.4, 5.0),  # shelf against the west wall
    (1.0, 6.9, 2.8, 7.6),  # desk
    (6.0, 6.9, 7.6, 7.6),  # table
    (8.6, 0.0, 10.0, 0.6),  # cabinet in the south-east corner
    (5.2, 2.6, 5.6, 3.0),  # column inside the loop
)
_OFFICE_CRATE_A = (3.6, 3.2, 4.4, 4.0)
_OFFICE_CRATE_B = (6.2, 3.6, 7.0, 4.4)
_OFFICE_DOOR = (10.0, 3.0, 10.1, 3.9)
_OFFICE_LOOP = ((5.0, 4.0), (3.2, 2.4))  # centre, semi-axes
_PERSON_STEP = 0.6  # metres walked per scan
_PERSON_PATHS = (((0.8, 5.3), (9.2, 5.3)), ((9.2, 7.4), (9.2, 1.0)))
_OFFICE_EXTENT = ((-0.2, -0.2), (12.4, 8.2))


def simulate_dynamic_office(
    n_scans: int = 140,
    *,
    scans_per_lap: int = 40,
    n_beams: int = 180,
    fov: float = float(2 * np.pi),
    max_range: float = 8.0,
    crate_moves_at: int = 45,
    door_opens_at: int = 60,
    people_start: tuple[int, ...] = (70, 96),
) -> DynamicScene:
    """Simulate a 2D office in which a crate moves, a door opens and people walk by.

    The office (10 x 8 m inside, walls 0.2 m thick; a shelf, a desk, a table, a
    cabinet and a column) has a 0.9 m door in its east wall onto a 2 m corridor. The
    robot drives an elliptic loop (semi-axes 3.2 x 2.4 m about the room's centre),
    ``scans_per_lap`` scans a lap, casting ``n_beams`` beams over ``fov`` centred on
    its heading.

    Objects (:attr:`DynamicScene.objects`, in this order):

    - ``"crate"``: a 0.8 m box at A (inside the loop) until ``crate_moves_at``, then at B;
    - ``"door"``: 0.1 m thick, filling the door gap, until ``door_opens_at``;
    - ``"person 1"``, ``"person 2"``, ...: 0.4 m boxes walking 0.6 m a scan from
      ``people_start[k]`` on, the first west to east across the room (crossing the
      loop), the second north to south along the east side.

    Parameters
    ----------
    n_scans : int
        Scans, ``>= 2``.
    scans_per_lap : int
        Scans per lap of the loop, ``>= 2``.
    n_beams : int
        Beams per scan.
    fov : float
        Field of view, radians; ``2 * pi`` (default) is a full circle.
    max_range : float
        No-return range, metres.
    crate_moves_at, door_opens_at : int
        First scan with the crate at B, first scan with the door open.
    people_start : tuple of int
        First scan of each person's walk (at most 2 people).

    Returns
    -------
    DynamicScene

    Raises
    ------
    OctolgpError
        On a bad count, or timings that put a person on the robot.
    """
    _check_int("simulate_dynamic_office: n_scans", n_scans, 2)
    _check_int("simulate_dynamic_office: scans_per_lap", scans_per_lap, 2)
    _check_int("simulate_dynamic_office: n_beams", n_beams, 1)
    _check_int("simulate_dynamic_office: crate_moves_at", crate_moves_at, 0)
    _check_int("simulate_dynamic_office: door_opens_at", door_opens_at, 0)
    if len(people_start) > len(_PERSON_PATHS):
        raise OctolgpError(f"simulate_dynamic_office: at most {len(_PERSON_PATHS)} people")
    for start in people_start:
        _check_int("simulate_dynamic_office: people_start", start, 0)
    if not (np.isfinite(fov) and 0 < fov <= 2 * np.pi):
        raise OctolgpError(f"simulate_dynamic_office: fov must be in (0, 2 pi], got {fov!r}")
    if not (np.isfinite(max_range) and max_range > 0):
        raise OctolgpError(f"simulate_dynamic_office: max_range must be > 0, got {max_range!r}")
    if fov >= 2 * np.pi:
        angles = np.linspace(-np.pi, np.pi, n_beams, endpoint=False)
    else:
        angles = np.linspace(-fov / 2, fov / 2, n_beams)
    objects = [
        DynamicObject(
            "crate",
            "box",
            _schedule(
                n_scans,
                [
                    (0, crate_moves_at, list(_OFFICE_CRATE_A)),
                    (crate_moves_at, n_scans, list(_OFFICE_CRATE_B)),
                ],
            ),
        ),
        DynamicObject("door", "door", _schedule(n_scans, [(0, door_opens_at, list(_OFFICE_DOOR))])),
    ]
    for k, start in enumerate(people_start):
        a, b = _PERSON_PATHS[k]
        objects.append(
            DynamicObject(f"person {k + 1}", "person", _walk(n_scans, start, a, b, _PERSON_STEP))
        )
    shifted = [DynamicObject(o.name, o.kind, o.boxes + SHIFT_2D) for o in objects]  # NaN stays
    poses = _loop_poses(n_scans, scans_per_lap, *_OFFICE_LOOP)
    poses[:, :2] += SHIFT_2D
    return DynamicScene(
        name="2D office: crate A->B, door opens, 2 people cross",
        static_boxes=np.asarray(_OFFICE_STATIC) + SHIFT_2D,
        objects=tuple(shifted),
        poses=poses,
        directions=np.column_stack([np.cos(angles), np.sin(angles)]),
        max_range=float(max_range),
        voxel_filter=None,
        extent=np.asarray(_OFFICE_EXTENT) + SHIFT_2D,
    )


# 3D room, metres before SHIFT_3D (every coordinate a multiple of 0.2 m): interior
# [0, 8] x [0, 6] x [0, 3], walls 0.2 m thick.
_ROOM_STATIC = (
    (-0.2, -0.2, -0.2, 8.2, 6.2, 0.0),  # floor
    (-0.2, -0.2, 3.0, 8.2, 6.2, 3.2),  # ceiling
    (-0.2, -0.2, 0.0, 0.0, 6.2, 3.0),  # west wall
    (8.0, -0.2, 0.0, 8.2, 6.2, 3.0),  # east wall
    (0.0, -0.2, 0.0, 8.0, 0.0, 3.0),  # south wall
    (0.0, 6.0, 0.0, 8.0, 6.2, 3.0),  # north wall
    (0.0, 0.0, 0.0, 1.2, 0.6, 1.8),  # cabinet, south-west corner
    (5.6, 4.8, 0.0, 7.2, 5.6, 0.8),  # table-high block
    (3.8, 5.2, 0.0, 4.2, 5.6, 3.0),  # pillar
)
_ROOM_CUBE_A = (2.4, 2.4, 0.0, 3.4, 3.4, 1.0)
_ROOM_CUBE_B = (4.8, 2.6, 0.0, 5.8, 3.6, 1.0)
_ROOM_LOOP = ((4.0, 3.0), (2.6, 1.7))
_ROOM_SENSOR_HEIGHT = 0.8
_ROOM_EXTENT = ((-0.2, -0.2, -0.2), (8.2, 6.2, 3.2))


def simulate_dynamic_room3d(
    n_scans: int = 48,
    *,
    scans_per_lap: int = 16,
    n_azimuth: int = 360,
    n_elevation: int = 16,
    fov_down: float = -25.0,
    fov_up: float = 15.0,
    max_range: float = 10.0,
    cube_moves_at: int = 16,
    voxel_filter: float | None = 0.2,
) -> DynamicScene:
    """Simulate a 3D room in which a 1 m cube moves from A to B, seen by a spinning lidar.

    The room is 8 x 6 x 3 m inside (floor, ceiling and walls 0.2 m thick) with a
    cabinet, a table-high block and a pillar. The lidar, ``0.8`` m above the floor,
    drives an elliptic loop (semi-axes 2.6 x 1.7 m about the room's centre, the cube
    inside it), ``scans_per_lap`` scans a lap, casting ``n_elevation`` rings of
    ``n_azimuth`` beams (:func:`octolgp.sim.lidar3d.beam_pattern`).

    Objects: ``"cube"``, at A until ``cube_moves_at``, then at B.

    Parameters
    ----------
    n_scans, scans_per_lap : int
        Scans, and scans per lap of the loop (both ``>= 2``).
    n_azimuth, n_elevation : int
        Beams per ring and rings.
    fov_down, fov_up : float
        Elevation of the lowest and highest ring, degrees.
    max_range : float
        No-return range, metres.
    cube_moves_at : int
        First scan with the cube at B.
    voxel_filter : float or None
        Edge of the voxel-grid filter applied to each scan (:meth:`Scan.downsample`);
        ``None`` keeps every beam.

    Returns
    -------
    DynamicScene

    Raises
    ------
    OctolgpError
        On a bad count, field of view or range.
    """
    for name, value, low in (
        ("n_scans", n_scans, 2),
        ("scans_per_lap", scans_per_lap, 2),
        ("n_azimuth", n_azimuth, 1),
        ("n_elevation", n_elevation, 1),
        ("cube_moves_at", cube_moves_at, 0),
    ):
        _check_int(f"simulate_dynamic_room3d: {name}", value, low)
    if not (-90.0 <= fov_down < fov_up <= 90.0):
        raise OctolgpError("simulate_dynamic_room3d: need -90 <= fov_down < fov_up <= 90")
    if not (np.isfinite(max_range) and max_range > 0):
        raise OctolgpError(f"simulate_dynamic_room3d: max_range must be > 0, got {max_range!r}")
    if voxel_filter is not None and not (np.isfinite(voxel_filter) and voxel_filter > 0):
        raise OctolgpError(f"simulate_dynamic_room3d: bad voxel_filter {voxel_filter!r}")
    cube = _schedule(
        n_scans,
        [(0, cube_moves_at, list(_ROOM_CUBE_A)), (cube_moves_at, n_scans, list(_ROOM_CUBE_B))],
    )
    planar = _loop_poses(n_scans, scans_per_lap, *_ROOM_LOOP)
    poses = np.column_stack([planar[:, :2], np.full(n_scans, _ROOM_SENSOR_HEIGHT), planar[:, 2]])
    poses[:, :3] += SHIFT_3D
    return DynamicScene(
        name="3D room: 1 m cube A->B",
        static_boxes=np.asarray(_ROOM_STATIC) + SHIFT_3D,
        objects=(DynamicObject("cube", "cube", cube + SHIFT_3D),),
        poses=poses,
        directions=beam_pattern(n_azimuth, n_elevation, fov_down, fov_up),
        max_range=float(max_range),
        voxel_filter=voxel_filter,
        extent=np.asarray(_ROOM_EXTENT) + SHIFT_3D,
    )
