"""nav2 ``map_server`` maps: a trinary PGM image with its YAML, from a 2D map or a 3D map's slice.

The format is ROS's ``map_server`` map (nav2 ``nav2_map_server/src/map_io.cpp``; ROS 1
``map_server``'s documentation):

- ``FILE.pgm``: a binary greyscale image (``P5``, maxval 255), one pixel per cell, rows from the
  top of the map (largest y) down. With ``negate: 0`` and ``mode: trinary``, as nav2's
  ``map_saver`` writes them: occupied cells are 0 (black), free cells 254, unknown cells 205.
- ``FILE.yaml``: ``image`` (relative to the YAML), ``mode``, ``resolution`` (metres per cell),
  ``origin`` ``[x, y, yaw]`` (the lower-left corner of the lower-left cell, world frame, metres),
  ``negate``, ``occupied_thresh`` and ``free_thresh``.

The loader turns a pixel ``v`` into ``occ = 1 - v / 255``; occupied if ``occ >
occupied_thresh``, free if ``occ < free_thresh``, else unknown. Those thresholds must fall
between the three pixel values, so the YAML holds the fixed :data:`LOAD_OCCUPIED_THRESH` and
:data:`LOAD_FREE_THRESH` (0.65 and 0.196, what ROS 1's ``map_saver`` writes and nav2 writes
since navigation2 PR #5278: with nav2's older ``free_thresh: 0.25`` an unknown pixel, occ
0.196, loaded as free). The map's own thresholds on P(occupied) are the writer's
``occupied_thresh``/``free_thresh`` arguments, applied before the pixels are written.

A cell is unknown where the map has no voxel, where P is exactly 0.5 (no information), or
where P lies between ``free_thresh`` and ``occupied_thresh``.
:func:`octolgp.export.nav2_read.read_nav2_map` reads both files back as ``map_server`` does.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.export.common import PathLike, as_centres, as_prob, replacing, write_chunks
from octolgp.geometry.keys import addressable_range

__all__ = [
    "FREE",
    "LOAD_FREE_THRESH",
    "LOAD_OCCUPIED_THRESH",
    "OCCUPIED",
    "UNKNOWN",
    "TrinaryGrid",
    "cell_states",
    "project_cells",
    "trinary_grid",
    "write_nav2_map",
]

Int8Array = NDArray[np.int8]
FloatArray = NDArray[np.float64]

OCCUPIED, FREE, UNKNOWN = 100, 0, -1
"""Cell states, as ``nav_msgs/OccupancyGrid`` holds them."""
LOAD_OCCUPIED_THRESH = 0.65
"""``occupied_thresh`` in the YAML: above it, a pixel loads as occupied (pixel 0: occ 1)."""
LOAD_FREE_THRESH = 0.196
"""``free_thresh`` in the YAML: below it, a pixel loads as free (254: occ 0.004; 205: 0.196)."""

_PIXEL = MappingProxyType({OCCUPIED: 0, FREE: 254, UNKNOWN: 205})
_MAX_CELLS = 100_000_000


def _thresholds(occupied_thresh: float, free_thresh: float) -> None:
    """Refuse thresholds outside ``0 < free_thresh < occupied_thresh < 1``."""
    for name, value in (("occupied_thresh", occupied_thresh), ("free_thresh", free_thresh)):
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
            raise OctolgpError(f"{name} must be a number, got {value!r}")
    if not 0.0 < free_thresh < occupied_thresh < 1.0:
        raise OctolgpError(
            f"need 0 < free_thresh < occupied_thresh < 1, got free_thresh={free_thresh!r}, "
            f"occupied_thresh={occupied_thresh!r}"
        )


def cell_states(
    prob: ArrayLike, *, occupied_thresh: float = 0.65, free_thresh: float = 0.25
) -> Int8Array:
    """Threshold P(occupied) into cell states: :data:`OCCUPIED`, :data:`FREE`, :data:`UNKNOWN`.

    Parameters
    ----------
    prob : array_like of float, shape (k,)
        P(occupied) per voxel, in [0, 1].
    occupied_thresh, free_thresh : float
        Occupied where ``P > occupied_thresh``, free where ``P < free_thresh``; unknown in
        between and where P is exactly 0.5. ``0 < free_thresh < occupied_thresh < 1``.

    Returns
    -------
    ndarray of int8, shape (k,)

    Raises
    ------
    OctolgpError
        On bad thresholds or a ``prob`` that is not finite values in [0, 1].
    """
    _thresholds(occupied_thresh, free_thresh)
    p = np.asarray(prob)
    if p.ndim != 1:
        raise OctolgpError(f"prob must have shape (k,), got {p.shape}")
    p = as_prob(p, p.shape[0])
    states = np.full(p.shape, UNKNOWN, dtype=np.int8)
    states[p > occupied_thresh] = OCCUPIED
    states[p < free_thresh] = FREE
    states[p == 0.5] = UNKNOWN  # no information, whatever the thresholds
    return states


def _rank(states: Int8Array) -> NDArray[np.int64]:
    """Order for merging cells: unknown 0 < free 1 < occupied 2."""
    return np.where(states == OCCUPIED, 2, np.where(states == FREE, 1, 0))


def _merge(cells: NDArray[np.int64], states: Int8Array) -> tuple[NDArray[np.int64], Int8Array]:
    """One state per distinct cell index ``(k, 2)``: occupied if any is, else free if any is."""
    if not cells.shape[0]:
        return cells, states
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    if int(span[0]) * int(span[1]) < 2**62:  # packed into int64: a 1D unique, same order
        packed, inverse = np.unique(
            (cells[:, 0] - low[0]) * span[1] + (cells[:, 1] - low[1]), return_inverse=True
        )
        unique = np.column_stack([packed // span[1], packed % span[1]]) + low
    else:
        unique, inverse = np.unique(cells, axis=0, return_inverse=True)
    best = np.zeros(unique.shape[0], dtype=np.int64)
    np.maximum.at(best, inverse.ravel(), _rank(states))
    merged = np.choose(best, [UNKNOWN, FREE, OCCUPIED]).astype(np.int8)
    return unique, merged


def _slice(
    c: FloatArray, resolution: float, z: float | None, z_range: tuple[float, float] | None
) -> NDArray[np.bool_]:
    """Which voxels a 2D map's cells, or a 3D map's slice or projection, take (checks the arguments)."""
    if c.shape[1] == 2:
        if z is not None or z_range is not None:
            raise OctolgpError("z and z_range apply to 3D maps only; this map is 2D")
        return np.ones(c.shape[0], dtype=bool)
    if (z is None) == (z_range is None):
        raise OctolgpError(
            "a 3D map needs exactly one of z (a height slice) or z_range (a 2.5D projection)"
        )
    if z is not None:
        if not math.isfinite(z):
            raise OctolgpError(f"z must be finite, got {z!r}")
        out: NDArray[np.bool_] = np.floor(c[:, 2] / resolution) == math.floor(z / resolution)
        return out
    assert z_range is not None
    lo, hi = (float(v) for v in z_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise OctolgpError(f"z_range must be finite (zmin, zmax) with zmin <= zmax, got {z_range}")
    band: NDArray[np.bool_] = (c[:, 2] >= lo) & (c[:, 2] <= hi)
    return band


def _empty_slice(z: float | None, z_range: tuple[float, float] | None) -> OctolgpError:
    if z is not None:
        return OctolgpError(f"no voxel in the height slice z = {z:g} m")
    assert z_range is not None
    lo, hi = (float(v) for v in z_range)
    return OctolgpError(f"no voxel centre in z_range [{lo:g}, {hi:g}] m")


def project_cells(
    centres: ArrayLike,
    states: ArrayLike,
    resolution: float,
    *,
    z: float | None = None,
    z_range: tuple[float, float] | None = None,
) -> tuple[FloatArray, Int8Array]:
    """Cells of a 2D map, or of a 3D map's height slice or 2.5D projection.

    Parameters
    ----------
    centres : array_like of float, shape (k, 2) or (k, 3)
        Voxel centres, world frame, metres.
    states : array_like of int8, shape (k,)
        Their states (:func:`cell_states`).
    resolution : float
        Voxel edge, metres.
    z : float, optional
        3D: the voxels of the layer holding height ``z`` (metres), as the PNG export slices.
    z_range : (float, float), optional
        3D: the 2.5D projection of the voxels whose centres lie in ``[zmin, zmax]`` (metres): a
        column is occupied if any of them is occupied, else free if any is free, else unknown
        (voxels between the thresholds count as unobserved).

    Returns
    -------
    centres : ndarray of shape (c, 2)
        Distinct cell centres (x, y), metres.
    states : ndarray of int8, shape (c,)

    Raises
    ------
    OctolgpError
        On bad shapes, a bad ``resolution``, ``z``/``z_range`` with a 2D map or neither (or
        both) with a 3D one, an empty or non-finite ``z_range``, or no voxel in the slice.
    """
    addressable_range(resolution, 16)  # raises on a bad resolution
    c = as_centres(centres, (2, 3))
    s = np.asarray(states)
    if s.shape != (c.shape[0],) or s.dtype.kind not in "iu":
        raise OctolgpError(f"states must be integers of shape ({c.shape[0]},), got {s.shape}")
    s = s.astype(np.int8)
    inside = _slice(c, resolution, z, z_range)
    if c.shape[1] == 3 and not inside.any():
        raise _empty_slice(z, z_range)
    c, s = c[inside], s[inside]
    cells, merged = _merge(np.floor(c[:, :2] / resolution).astype(np.int64), s)
    return np.asarray((cells + 0.5) * resolution, dtype=np.float64), merged


@dataclass(frozen=True)
class TrinaryGrid:
    """A map as ``nav_msgs/OccupancyGrid`` holds it: cells 100, 0 or -1.

    Attributes
    ----------
    data : ndarray of int8, shape (height, width)
        :data:`OCCUPIED` (100), :data:`FREE` (0) or :data:`UNKNOWN` (-1) per cell; row 0 is
        the smallest y, column 0 the smallest x (``OccupancyGrid.data`` is ``data.ravel()``).
    origin : tuple of float
        ``(x, y)`` of the lower-left corner of cell (0, 0), world frame, metres.
    resolution : float
        Metres per cell.
    """

    data: Int8Array
    origin: tuple[float, float]
    resolution: float


def trinary_grid(
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    z: float | None = None,
    z_range: tuple[float, float] | None = None,
) -> TrinaryGrid:
    """The cells of a map by its thresholds, as a nav2 ``OccupancyGrid`` (trinary).

    Every cell the PGM of :func:`write_nav2_map` makes black is 100 (lethal to nav2's
    static layer), white 0 and grey -1: the two are one rasterisation.

    Parameters
    ----------
    centres, prob, resolution, occupied_thresh, free_thresh, z, z_range
        As :func:`write_nav2_map`.

    Raises
    ------
    OctolgpError
        On bad arrays, thresholds or slice arguments, no voxel, or more than 10^8 cells.
    """
    return trinary_grid_chunks(
        [(centres, prob)],
        resolution,
        occupied_thresh=occupied_thresh,
        free_thresh=free_thresh,
        z=z,
        z_range=z_range,
    )


def trinary_grid_chunks(
    chunks: Iterable[tuple[ArrayLike, ArrayLike]],
    resolution: float,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    z: float | None = None,
    z_range: tuple[float, float] | None = None,
) -> TrinaryGrid:
    """:func:`trinary_grid` of a map read in chunks of voxels (``MapReads.voxel_chunks``).

    Each chunk is thresholded and merged into its cells on its own (a cell is occupied
    if any of its voxels is, else free if any is), so what is held is one chunk and
    the cells; the grid is that of the chunks concatenated.

    Parameters
    ----------
    chunks : iterable of (centres, prob)
        Voxel centres, shape (k, 2) or (k, 3), and P(occupied), shape (k,).
    resolution, occupied_thresh, free_thresh, z, z_range
        As :func:`write_nav2_map`.

    Raises
    ------
    OctolgpError
        As :func:`trinary_grid`.
    """
    addressable_range(resolution, 16)  # raises on a bad resolution
    _thresholds(occupied_thresh, free_thresh)
    cells, states, dim = [], [], 0
    for centres, prob in chunks:  # one chunk of voxels per iteration
        c = as_centres(centres, (2, 3))
        dim = c.shape[1]
        s = cell_states(
            as_prob(prob, c.shape[0]), occupied_thresh=occupied_thresh, free_thresh=free_thresh
        )
        inside = _slice(c, resolution, z, z_range)
        index, merged = _merge(np.floor(c[inside, :2] / resolution).astype(np.int64), s[inside])
        cells.append(index)
        states.append(merged)
    index, cell_state = _merge(
        np.concatenate([np.zeros((0, 2), np.int64), *cells]),
        np.concatenate([np.zeros(0, np.int8), *states]),
    )
    if not index.shape[0]:
        if dim == 3:
            raise _empty_slice(z, z_range)
        raise OctolgpError("nav2 map: the map has no voxel to write")
    low = index.min(axis=0)
    nx, ny = (index.max(axis=0) - low + 1).tolist()
    if nx * ny > _MAX_CELLS:
        raise OctolgpError(f"nav2 map: {nx} x {ny} cells at resolution {resolution:g} is too many")
    data = np.full((ny, nx), UNKNOWN, dtype=np.int8)
    rel = index - low
    data[rel[:, 1], rel[:, 0]] = cell_state
    origin = low * resolution
    return TrinaryGrid(data, (float(origin[0]), float(origin[1])), float(resolution))


def write_nav2_map(
    path: PathLike,
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    z: float | None = None,
    z_range: tuple[float, float] | None = None,
) -> Path:
    """Write a map as a nav2 ``map_server`` map: ``FILE.pgm`` and ``FILE.yaml`` beside it.

    Parameters
    ----------
    path : str or os.PathLike
        The image, ending in ``.pgm``; the YAML gets the same name ending in ``.yaml``.
    centres : array_like of float, shape (k, 2) or (k, 3)
        Voxel centres in the world frame, metres (``OnlineMap.voxels()``).
    prob : array_like of float, shape (k,)
        P(occupied) per voxel, in [0, 1].
    resolution : float
        Voxel edge, metres; one pixel per cell.
    occupied_thresh, free_thresh : float
        The map's thresholds on P (:func:`cell_states`); the YAML holds the loader's own
        (:data:`LOAD_OCCUPIED_THRESH`, :data:`LOAD_FREE_THRESH`).
    z, z_range : optional
        For a 3D map, a height slice or a 2.5D projection (:func:`project_cells`).

    Returns
    -------
    Path
        The YAML file (give it to ``map_server`` as ``yaml_filename``).

    Raises
    ------
    OctolgpError
        On a ``path`` not ending in ``.pgm``, bad arrays, thresholds or slice arguments, a
        map wider than 10^8 cells, or files that cannot be written.
    """
    _pgm_path(path)
    cells = trinary_grid(
        centres,
        prob,
        resolution,
        occupied_thresh=occupied_thresh,
        free_thresh=free_thresh,
        z=z,
        z_range=z_range,
    )
    return write_nav2_grid(path, cells, occupied_thresh=occupied_thresh, free_thresh=free_thresh)


def _pgm_path(path: PathLike) -> Path:
    pgm = Path(path)
    if pgm.suffix.lower() != ".pgm":
        raise OctolgpError(f"nav2 map: path must end in .pgm, got {os.fspath(path)!r}")
    return pgm


def write_nav2_grid(
    path: PathLike, cells: TrinaryGrid, *, occupied_thresh: float, free_thresh: float
) -> Path:
    """Write a :class:`TrinaryGrid` as ``FILE.pgm`` and ``FILE.yaml`` (:func:`write_nav2_map`).

    ``occupied_thresh`` and ``free_thresh`` are the map's thresholds the grid was made
    with, noted in the YAML; the YAML's own are the loader's.

    Returns
    -------
    Path
        The YAML file.
    """
    pgm = _pgm_path(path)
    resolution = cells.resolution
    ny, nx = cells.data.shape
    # state -> pixel: FREE 0 -> 254, OCCUPIED 100 -> 0, UNKNOWN -1 -> 205
    grid = np.full((ny, nx), _PIXEL[UNKNOWN], dtype=np.uint8)
    grid[cells.data == FREE] = _PIXEL[FREE]
    grid[cells.data == OCCUPIED] = _PIXEL[OCCUPIED]
    grid = grid[::-1]  # image row 0 is the largest y
    header = f"P5\n# octolgp occupancy, {float(resolution)!r} m per cell\n{nx} {ny}\n255\n"
    origin = cells.origin
    yaml = pgm.with_suffix(".yaml")
    occ, free = float(occupied_thresh), float(free_thresh)
    text = (
        f"# octolgp: P(occupied) > {occ!r} occupied, < {free!r} free; the thresholds\n"
        "# below are the loader's, between the trinary pixels 0, 205 and 254.\n"
        f"image: {pgm.name}\nmode: trinary\nresolution: {float(resolution)!r}\n"
        f"origin: [{float(origin[0])!r}, {float(origin[1])!r}, 0.0]\nnegate: 0\n"
        f"occupied_thresh: {LOAD_OCCUPIED_THRESH!r}\nfree_thresh: {LOAD_FREE_THRESH!r}\n"
    )
    # both files are written in full before either is renamed into place
    with replacing(pgm) as pgm_tmp:
        write_chunks(pgm_tmp, [header.encode("ascii"), grid.tobytes()])
        with replacing(yaml) as yaml_tmp:
            write_chunks(yaml_tmp, [text.encode("utf-8")])
    return yaml
