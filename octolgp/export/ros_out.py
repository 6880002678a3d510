"""ROS 2 map messages as plain arrays: what a ROS node publishes of a map, without ``rclpy``.

A node fills its messages field by field from these results; nothing here imports ROS, so
each message's content is built and tested without it.

- ``nav_msgs/OccupancyGrid``: :func:`map_grid` rasterises a map (a 2D map, or a 3D map's
  2.5D projection) into a trinary grid by the map's thresholds, 100 lethal to nav2's static
  layer, 0 free, -1 unknown, cell for cell what :func:`~octolgp.export.nav2.write_nav2_map`
  writes; its origin and size are whole tiles, so a map growing inside its tiles keeps the
  grid's geometry. :func:`grid_message` gives the message's ``info`` and ``data``.
- ``map_msgs/OccupancyGridUpdate``: :func:`grid_updates` gives rectangles covering every
  cell that changed between two grids of one geometry (``None`` when the geometry changed
  and only a full grid will do); :func:`apply_updates` applies them as nav2's static layer
  does, giving the new grid exactly. :class:`GridSync` decides, publish by publish, between
  a full grid and updates.
- ``octomap_msgs/Octomap``: :func:`octomap_binary` is the tree stream ``octomap_server``
  publishes (``binary`` true, ``id`` ``OcTree``): the bytes after the header of a ``.bt``
  file (:func:`octolgp.export.octomap.bt_data`).
- ``visualization_msgs/Marker`` (``CUBE_LIST``): :func:`occupied_cubes` gives the occupied
  voxels' centres and colours by height, as ``octomap_server``'s ``occupied_cells_vis_array``.

Cells and voxels are classified once, by :func:`~octolgp.export.nav2.cell_states`: occupied
where ``P > occupied_thresh``, free where ``P < free_thresh``, unknown between and where
``P`` is exactly 0.5. Coordinates are in the map's (fixed) frame, metres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.export.common import as_centres, as_prob
from octolgp.export.nav2 import OCCUPIED, UNKNOWN, TrinaryGrid, cell_states, trinary_grid
from octolgp.export.octomap import bt_data
from octolgp.geometry.keys import coord_to_key

__all__ = [
    "CubeList",
    "GridMessage",
    "GridSync",
    "GridUpdate",
    "OctomapMessage",
    "apply_updates",
    "clip_z_range",
    "grid_message",
    "grid_updates",
    "height_colours",
    "map_grid",
    "occupied_cubes",
    "octomap_binary",
    "trinary_voxels",
]

Int8Array = NDArray[np.int8]
FloatArray = NDArray[np.float64]
A = TypeVar("A", bound=NDArray[Any])

OCTOMAP_ID = "OcTree"
"""``octomap_msgs/Octomap.id`` of an occupancy tree (OctoMap's ``OcTree::getTreeType()``)."""


def _frozen(a: A) -> A:
    """``a`` made read-only, so a frozen dataclass holding it cannot change."""
    a.setflags(write=False)
    return a


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise OctolgpError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


# ------------------------------------------------------------------ OccupancyGrid


@dataclass(frozen=True)
class GridMessage:
    """The fields of a ``nav_msgs/OccupancyGrid`` (``info`` and ``data``).

    Attributes
    ----------
    width, height : int
        Cells along x and y (``info.width``, ``info.height``).
    resolution : float
        Metres per cell (``info.resolution``).
    origin : tuple of float
        ``(x, y)`` of the lower-left corner of cell (0, 0), map frame, metres
        (``info.origin.position``; the orientation is the identity).
    data : ndarray of int8, shape (height * width,)
        Row-major from cell (0, 0): cell ``(col, row)`` at ``data[row * width + col]``,
        rows along +y (``OccupancyGrid.data``); 100 occupied, 0 free, -1 unknown.
    """

    width: int
    height: int
    resolution: float
    origin: tuple[float, float]
    data: Int8Array


def grid_message(grid: TrinaryGrid) -> GridMessage:
    """The ``OccupancyGrid`` fields of a trinary grid.

    Parameters
    ----------
    grid : TrinaryGrid
        From :func:`map_grid` or :func:`~octolgp.export.nav2.trinary_grid`.

    Returns
    -------
    GridMessage

    Raises
    ------
    OctolgpError
        If ``grid`` is not a :class:`~octolgp.export.nav2.TrinaryGrid` of int8 cells.
    """
    data = _grid_data(grid, "grid")
    height, width = data.shape
    flat = _frozen(np.ascontiguousarray(data).reshape(-1).copy())
    return GridMessage(width, height, grid.resolution, grid.origin, flat)


def _grid_data(grid: object, name: str) -> Int8Array:
    if not isinstance(grid, TrinaryGrid):
        raise OctolgpError(f"{name} must be a TrinaryGrid, got {type(grid).__name__}")
    data = np.asarray(grid.data)
    if data.ndim != 2 or data.dtype != np.int8:
        raise OctolgpError(f"{name}.data must be int8 of shape (height, width), got {data.shape}")
    return data


def clip_z_range(centres: ArrayLike, z_range: tuple[float, float]) -> tuple[float, float]:
    """A height band with infinite ends brought in to the lowest and highest voxel centre.

    Parameters
    ----------
    centres : array_like of float, shape (k, 3)
        Voxel centres, map frame, metres.
    z_range : (float, float)
        ``(zmin, zmax)``, metres, ``zmin <= zmax``; either end may be infinite.

    Returns
    -------
    (float, float)
        The band, finite where the map has voxels (what
        :func:`~octolgp.export.nav2.project_cells` takes).

    Raises
    ------
    OctolgpError
        On bad centres, or a ``z_range`` that is not two numbers with ``zmin <= zmax``.
    """
    c = as_centres(centres, (3,))
    try:
        lo, hi = (float(v) for v in z_range)
    except (TypeError, ValueError):
        raise OctolgpError(f"z_range must be two numbers (zmin, zmax), got {z_range!r}") from None
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise OctolgpError(f"z_range must be (zmin, zmax) with zmin <= zmax, got {z_range!r}")
    if c.shape[0]:  # an infinite end moves in, never past the other end
        if math.isinf(lo):
            lo = min(float(c[:, 2].min()), hi)
        if math.isinf(hi):
            hi = max(float(c[:, 2].max()), lo)
    return lo, hi


def map_grid(
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    z_range: tuple[float, float] = (-math.inf, math.inf),
    tile: int = 32,
) -> TrinaryGrid:
    """A map's trinary ``OccupancyGrid``, its origin and size whole tiles.

    The cells are those of :func:`~octolgp.export.nav2.trinary_grid` (the nav2 PGM's), set
    into a grid whose corners lie on the lattice of ``tile`` x ``tile`` cells from the world
    origin; the padding is unknown. So the grid keeps its geometry, and :func:`grid_updates`
    applies, until the map grows out of its tiles.

    Parameters
    ----------
    centres : array_like of float, shape (k, 2) or (k, 3)
        Voxel centres, map frame, metres (``OnlineMap.voxels()``).
    prob : array_like of float, shape (k,)
        P(occupied) per voxel.
    resolution : float
        Voxel edge, metres; one cell per voxel column.
    occupied_thresh, free_thresh : float
        The map's thresholds (:func:`~octolgp.export.nav2.cell_states`).
    z_range : (float, float), optional
        3D maps: the 2.5D projection of the voxels with centres in ``[zmin, zmax]``, metres;
        infinite ends reach the map's lowest and highest voxels (default: all of them).
        Ignored for 2D maps.
    tile : int, optional
        Tile edge in cells.

    Returns
    -------
    TrinaryGrid

    Raises
    ------
    OctolgpError
        On bad arrays, thresholds, ``z_range`` or ``tile``, no voxel (in the band), or a
        grid over 10^8 cells.
    """
    t = _positive_int(tile, "tile")
    c = as_centres(centres, (2, 3))
    band = None if c.shape[1] == 2 else clip_z_range(c, z_range)
    cells = trinary_grid(
        c, prob, resolution, occupied_thresh=occupied_thresh, free_thresh=free_thresh, z_range=band
    )
    ny, nx = cells.data.shape
    low = np.rint(np.asarray(cells.origin) / cells.resolution).astype(np.int64)
    start = (low // t) * t  # tile lattice from the world origin
    stop = -((-(low + np.array([nx, ny]))) // t) * t
    width, height = (stop - start).tolist()
    data = np.full((height, width), UNKNOWN, dtype=np.int8)
    dx, dy = (low - start).tolist()
    data[dy : dy + ny, dx : dx + nx] = cells.data
    origin = start * cells.resolution
    return TrinaryGrid(data, (float(origin[0]), float(origin[1])), cells.resolution)


# ------------------------------------------------------------------ OccupancyGridUpdate


@dataclass(frozen=True)
class GridUpdate:
    """The fields of a ``map_msgs/OccupancyGridUpdate``: a rectangle of new cells.

    Attributes
    ----------
    x, y : int
        Column and row of the rectangle's first cell in the full grid.
    width, height : int
        Its size in cells.
    data : ndarray of int8, shape (height * width,)
        Its cells, row-major as ``OccupancyGrid.data``.
    """

    x: int
    y: int
    width: int
    height: int
    data: Int8Array


def _runs(flags: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of True in a 1D array."""
    edges = np.flatnonzero(np.diff(np.concatenate([[False], flags, [False]]).astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def grid_updates(
    old: TrinaryGrid | None, new: TrinaryGrid, *, tile: int = 32, max_updates: int = 16
) -> list[GridUpdate] | None:
    """Rectangles of ``new`` covering every cell that differs from ``old``.

    Changed tiles (``tile`` x ``tile`` cells from cell (0, 0)) are joined into runs along
    each row of tiles, runs spanning the same tiles in consecutive rows into one
    rectangle, and each rectangle is shrunk to the changed cells it holds. More than
    ``max_updates`` rectangles become their one bounding rectangle (a subscriber's queue
    need not hold more).

    Parameters
    ----------
    old : TrinaryGrid or None
        The grid last published in full, with the updates since applied (what
        subscribers hold).
    new : TrinaryGrid
        The grid now.
    tile : int, optional
        Tile edge, cells.
    max_updates : int, optional
        The most rectangles returned.

    Returns
    -------
    list of GridUpdate or None
        Empty when nothing changed; ``None`` when ``old`` is ``None`` or differs from
        ``new`` in size, origin or resolution: publish ``new`` in full.

    Raises
    ------
    OctolgpError
        If a grid is not a :class:`~octolgp.export.nav2.TrinaryGrid` of int8 cells, or on a
        bad ``tile`` or ``max_updates``.
    """
    t = _positive_int(tile, "tile")
    most = _positive_int(max_updates, "max_updates")
    b = _grid_data(new, "new")
    if old is None:
        return None
    a = _grid_data(old, "old")
    if a.shape != b.shape or old.origin != new.origin or old.resolution != new.resolution:
        return None
    changed = a != b
    if not changed.any():
        return []
    h, w = changed.shape
    ty, tx = -(-h // t), -(-w // t)
    padded = np.zeros((ty * t, tx * t), dtype=bool)
    padded[:h, :w] = changed
    tiles = np.asarray(padded.reshape(ty, t, tx, t).any(axis=(1, 3)))
    rects: list[tuple[int, int, int, int]] = []  # tile rows [r0, r1), tile columns [c0, c1)
    open_runs: dict[tuple[int, int], int] = {}  # (c0, c1) -> first tile row
    for r in range(ty + 1):  # one pass per row of tiles
        runs = set(_runs(tiles[r])) if r < ty else set()
        for run in list(open_runs):
            if run not in runs:
                rects.append((open_runs.pop(run), r, *run))
        for run in runs:
            open_runs.setdefault(run, r)
    boxes = []
    for r0, r1, c0, c1 in rects:
        y0, y1, x0, x1 = r0 * t, min(r1 * t, h), c0 * t, min(c1 * t, w)
        block = changed[y0:y1, x0:x1]
        rows, cols = np.flatnonzero(block.any(axis=1)), np.flatnonzero(block.any(axis=0))
        boxes.append((y0 + rows[0], y0 + rows[-1] + 1, x0 + cols[0], x0 + cols[-1] + 1))
    if len(boxes) > most:
        ys0, ys1, xs0, xs1 = zip(*boxes, strict=True)
        boxes = [(min(ys0), max(ys1), min(xs0), max(xs1))]
    return [
        GridUpdate(
            int(x0),
            int(y0),
            int(x1 - x0),
            int(y1 - y0),
            _frozen(b[y0:y1, x0:x1].reshape(-1).copy()),
        )
        for y0, y1, x0, x1 in sorted(boxes)
    ]


def apply_updates(grid: TrinaryGrid, updates: Iterable[GridUpdate]) -> TrinaryGrid:
    """A grid with updates applied in order, as nav2's static layer applies them.

    Parameters
    ----------
    grid : TrinaryGrid
    updates : iterable of GridUpdate

    Returns
    -------
    TrinaryGrid
        A new grid; ``grid`` is unchanged.

    Raises
    ------
    OctolgpError
        If an update reaches outside the grid or its ``data`` is not ``width * height``
        cells.
    """
    data = _grid_data(grid, "grid").copy()
    h, w = data.shape
    for i, u in enumerate(updates):
        if not (u.x >= 0 and u.y >= 0 and u.x + u.width <= w and u.y + u.height <= h):
            raise OctolgpError(
                f"updates[{i}]: x, y, width, height = {u.x}, {u.y}, {u.width}, {u.height} "
                f"reach outside the {w} x {h} grid"
            )
        if np.shape(u.data) != (u.width * u.height,):
            raise OctolgpError(
                f"updates[{i}].data must have {u.width * u.height} cells, got {np.shape(u.data)}"
            )
        data[u.y : u.y + u.height, u.x : u.x + u.width] = np.reshape(u.data, (u.height, u.width))
    return TrinaryGrid(data, grid.origin, grid.resolution)


class GridSync:
    """What to send on a grid topic so its subscribers hold the newest grid.

    A full grid goes out first, whenever the grid's size, origin or resolution changes, and
    every ``full_period`` seconds (for subscribers that missed updates); in between, the
    :func:`grid_updates` from the grid subscribers hold.

    Parameters
    ----------
    tile, max_updates : int, optional
        As :func:`grid_updates`.
    full_period : float, optional
        Seconds between full grids, ``>= 0`` (0: every grid in full).

    Raises
    ------
    OctolgpError
        On a bad ``tile``, ``max_updates`` or ``full_period``.
    """

    def __init__(self, *, tile: int = 32, max_updates: int = 16, full_period: float = 10.0):
        self.tile = _positive_int(tile, "tile")
        self.max_updates = _positive_int(max_updates, "max_updates")
        ok = isinstance(full_period, int | float) and not isinstance(full_period, bool)
        if not ok or math.isnan(full_period) or full_period < 0:
            raise OctolgpError(f"full_period must be a number >= 0 seconds, got {full_period!r}")
        self.full_period = float(full_period)
        self.sent: TrinaryGrid | None = None  # what subscribers hold
        self._full_at = -math.inf

    def next(self, grid: TrinaryGrid, now: float) -> GridMessage | list[GridUpdate]:
        """The message(s) that bring subscribers from the last grid sent to ``grid``.

        Parameters
        ----------
        grid : TrinaryGrid
            The grid now (:func:`map_grid`).
        now : float
            Seconds on a monotonic clock.

        Returns
        -------
        GridMessage or list of GridUpdate
            A full grid, or the updates (empty when nothing changed).
        """
        changes = None
        if now - self._full_at < self.full_period:
            changes = grid_updates(self.sent, grid, tile=self.tile, max_updates=self.max_updates)
        self.sent = grid  # the old grid with the updates applied, cell for cell
        if changes is None:
            self._full_at = now
            return grid_message(grid)
        return changes


# ------------------------------------------------------------------ Octomap


def trinary_voxels(
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    tree_depth: int = 16,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """OctoMap keys of a map's known voxels and whether each is occupied.

    Parameters
    ----------
    centres : array_like of float, shape (k, 2) or (k, 3)
        Voxel centres, map frame, metres.
    prob : array_like of float, shape (k,)
        P(occupied) per voxel.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        The map's tree depth (``MapConfig.tree_depth``).
    occupied_thresh, free_thresh : float
        The map's thresholds; voxels between them (and at exactly 0.5) are left out,
        unknown as in OctoMap.

    Returns
    -------
    keys : ndarray of int64, shape (n, d)
        Keys of the occupied and free voxels (:func:`~octolgp.geometry.keys.coord_to_key`).
    occupied : ndarray of bool, shape (n,)

    Raises
    ------
    OctolgpError
        On bad arrays or thresholds, or a centre outside the addressable range.
    """
    c = as_centres(centres, (2, 3))
    states = cell_states(
        as_prob(prob, c.shape[0]), occupied_thresh=occupied_thresh, free_thresh=free_thresh
    )
    known = states != UNKNOWN
    keys = coord_to_key(c[known], resolution, tree_depth, name="centres")
    return keys, states[known] == OCCUPIED


@dataclass(frozen=True)
class OctomapMessage:
    """The fields of an ``octomap_msgs/Octomap`` holding a binary tree.

    Attributes
    ----------
    id : str
        ``"OcTree"``.
    binary : bool
        True: ``data`` is the max-likelihood tree stream (two bits per child).
    resolution : float
        Voxel edge, metres.
    data : bytes
        OctoMap's ``writeBinaryData`` stream (the ``.bt`` file after ``data``); the message's
        ``int8[] data`` holds these bytes.
    size : int
        Nodes in the tree, root and inner nodes included (0 for an empty tree).
    """

    id: str
    binary: bool
    resolution: float
    data: bytes
    size: int


def octomap_binary(
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    tree_depth: int = 16,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
) -> OctomapMessage:
    """A map as ``octomap_server`` publishes ``octomap_binary``.

    OctoMap's ``octomap_msgs::binaryMapToMsg`` fills the message from the same stream
    :func:`~octolgp.export.octomap.write_bt` writes after its header; ``fullMapToTree``
    reads it back. Occupied and free voxels are those of :func:`trinary_voxels`; a 2D map
    is one layer, z in ``[0, resolution)``.

    Parameters
    ----------
    centres, prob, resolution, tree_depth, occupied_thresh, free_thresh
        As :func:`trinary_voxels`.

    Returns
    -------
    OctomapMessage

    Raises
    ------
    OctolgpError
        As :func:`trinary_voxels`.
    """
    keys, occupied = trinary_voxels(
        centres,
        prob,
        resolution,
        tree_depth,
        occupied_thresh=occupied_thresh,
        free_thresh=free_thresh,
    )
    data, size = bt_data(keys, occupied, resolution, tree_depth)
    return OctomapMessage(OCTOMAP_ID, True, float(resolution), data, size)


# ------------------------------------------------------------------ MarkerArray


@dataclass(frozen=True)
class CubeList:
    """The fields of a ``visualization_msgs/Marker`` of type ``CUBE_LIST``.

    Attributes
    ----------
    points : ndarray of float64, shape (n, 3)
        Cube centres, map frame, metres (``points``).
    colours : ndarray of float32, shape (n, 4)
        RGBA in [0, 1] per cube (``colors``).
    scale : float
        Cube edge, metres (``scale.x``, ``.y`` and ``.z``).
    """

    points: FloatArray
    colours: NDArray[np.float32]
    scale: float


def height_colours(z: ArrayLike, color_factor: float = 0.8) -> NDArray[np.float32]:
    """RGBA by height, as ``octomap_server``'s ``heightMapColor``.

    The hue runs from ``color_factor`` at the lowest ``z`` down to 0 (red) at the
    highest, at full saturation and value.

    Parameters
    ----------
    z : array_like of float, shape (n,)
        Heights, metres.
    color_factor : float, optional
        The hue of the lowest cube, in [0, 1] (``octomap_server``'s ``color_factor``).

    Returns
    -------
    ndarray of float32, shape (n, 4)

    Raises
    ------
    OctolgpError
        On a ``z`` that is not finite numbers of shape (n,) or a bad ``color_factor``.
    """
    h = np.asarray(z)
    if h.ndim != 1 or h.dtype.kind not in "iuf" or not np.isfinite(h).all():
        raise OctolgpError(f"z must be finite numbers of shape (n,), got shape {h.shape}")
    if not isinstance(color_factor, int | float) or not 0.0 <= color_factor <= 1.0:
        raise OctolgpError(f"color_factor must be a number in [0, 1], got {color_factor!r}")
    out = np.ones((h.shape[0], 4), dtype=np.float32)
    if not h.size:
        return out
    span = float(h.max() - h.min())
    frac = (h - h.min()) / span if span > 0 else np.zeros(h.shape)
    hue = (1.0 - frac) * color_factor * 6.0  # HSV to RGB at s = v = 1: six sectors
    sector = np.floor(hue).astype(np.int64) % 6
    f = hue - np.floor(hue)
    rising, falling = f, 1.0 - f
    one, zero = np.ones_like(f), np.zeros_like(f)
    rgb = np.choose(
        sector[:, None],
        [
            np.c_[one, rising, zero],
            np.c_[falling, one, zero],
            np.c_[zero, one, rising],
            np.c_[zero, falling, one],
            np.c_[rising, zero, one],
            np.c_[one, zero, falling],
        ],
    )
    out[:, :3] = rgb
    return out


def occupied_cubes(
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    color_factor: float = 0.8,
) -> CubeList:
    """The occupied voxels as one ``CUBE_LIST`` marker, coloured by height.

    ``octomap_server``'s ``occupied_cells_vis_array`` holds one such marker per tree depth
    (pruned nodes are larger cubes); octolgp's voxels are all one size, so one marker
    holds them. A 2D map's cubes lie in the layer z in ``[0, resolution)``.

    Parameters
    ----------
    centres : array_like of float, shape (k, 2) or (k, 3)
        Voxel centres, map frame, metres.
    prob : array_like of float, shape (k,)
        P(occupied) per voxel.
    resolution : float
        Voxel edge, metres: the cube edge.
    occupied_thresh, free_thresh : float
        The map's thresholds; a cube per voxel with ``P > occupied_thresh``.
    color_factor : float, optional
        As :func:`height_colours`.

    Returns
    -------
    CubeList

    Raises
    ------
    OctolgpError
        On bad arrays, thresholds, ``resolution`` or ``color_factor``.
    """
    c = as_centres(centres, (2, 3))
    states = cell_states(
        as_prob(prob, c.shape[0]), occupied_thresh=occupied_thresh, free_thresh=free_thresh
    )
    if isinstance(resolution, bool) or not isinstance(resolution, int | float | np.floating):
        raise OctolgpError(f"resolution must be a number, got {resolution!r}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise OctolgpError(f"resolution must be finite and > 0, got {resolution!r}")
    occ = c[states == OCCUPIED]
    if c.shape[1] == 2:
        occ = np.c_[occ, np.full(occ.shape[0], 0.5 * resolution)]
    return CubeList(
        _frozen(np.ascontiguousarray(occ)),
        _frozen(height_colours(occ[:, 2], color_factor)),
        float(resolution),
    )
