"""Reading nav2 ``map_server`` maps (YAML and PGM) back into cell states, as ``map_server`` does.

The format and the writer are in :mod:`octolgp.export.nav2`. The YAML is read as the flat
``key: value`` file that map files are (scalars and ``[a, b, c]`` lists, ``#`` comments); the
image must be a binary PGM (``P5``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.export.common import PathLike, as_centres
from octolgp.export.nav2 import FREE, OCCUPIED, UNKNOWN

__all__ = ["Nav2Map", "read_nav2_map"]

Int8Array = NDArray[np.int8]
FloatArray = NDArray[np.float64]

_MODES = ("trinary", "scale")
_COMMENT = re.compile(r"(^|\s)#.*$")


@dataclass(frozen=True, eq=False)
class Nav2Map:
    """A nav2 map read back by :func:`read_nav2_map`.

    Attributes
    ----------
    cells : ndarray of int8, shape (ny, nx)
        ``nav_msgs/OccupancyGrid`` values: 100 occupied, 0 free, -1 unknown (trinary; scale
        mode also has values in between). Row 0 is the lowest y, as ``OccupancyGrid.data``.
    resolution : float
        Metres per cell.
    origin : tuple of 3 float
        ``(x, y, yaw)`` of the lower-left corner of cell ``[0, 0]``: metres, radians (the yaw
        is kept but, as in most of nav2, not applied).
    image : Path
        The image file.
    mode : str
        ``trinary`` or ``scale``.
    negate : bool
    occupied_thresh, free_thresh : float
        The loader's thresholds from the YAML, ``0 <= free_thresh < occupied_thresh <= 1``.
    """

    cells: Int8Array
    resolution: float
    origin: tuple[float, float, float]
    image: Path
    mode: str
    negate: bool
    occupied_thresh: float
    free_thresh: float

    def cell_centres(self) -> FloatArray:
        """Centres ``(ny * nx, 2)`` of :attr:`cells` in ``cells.ravel()`` order, metres."""
        ny, nx = self.cells.shape
        ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
        xy = np.column_stack([ix.ravel(), iy.ravel()]) + 0.5
        return np.asarray(xy * self.resolution + np.array(self.origin[:2]))

    def states_at(self, points: ArrayLike) -> Int8Array:
        """The cell value at each point ``(q, 2+)`` (x, y used); :data:`UNKNOWN` off the map."""
        p = as_centres(points, (2, 3))
        index = np.floor((p[:, :2] - np.array(self.origin[:2])) / self.resolution)
        ny, nx = self.cells.shape
        inside = (index >= 0).all(axis=1) & (index[:, 0] < nx) & (index[:, 1] < ny)
        out = np.full(p.shape[0], UNKNOWN, dtype=np.int8)
        i = index[inside].astype(np.int64)
        out[inside] = self.cells[i[:, 1], i[:, 0]]
        return out


def _yaml_value(text: str) -> str | list[str]:
    """A flat YAML scalar (quotes removed) or flow list ``[a, b, c]`` of scalars."""
    text = text.strip()
    if text.startswith("["):
        if not text.endswith("]"):
            raise ValueError(f"unclosed list {text[:60]!r}")
        return [t.strip().strip("'\"") for t in text[1:-1].split(",")]
    return text.strip("'\"")


def _read_yaml(path: Path) -> dict[str, tuple[int, str | list[str]]]:
    """``key -> (line, value)`` of a flat ``key: value`` YAML file, as map files are."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise OctolgpError(f"nav2 map {path}: unreadable: {exc}") from None
    entries: dict[str, tuple[int, str | list[str]]] = {}
    for i, line in enumerate(lines, start=1):
        body = _COMMENT.sub("", line)
        if not body.strip():
            continue
        key, colon, value = body.partition(":")
        if not colon or not key.strip() or key != key.lstrip():
            raise OctolgpError(f"nav2 map {path}:{i}: expected 'key: value', got {line[:80]!r}")
        try:
            entries[key.strip()] = (i, _yaml_value(value))
        except ValueError as exc:
            raise OctolgpError(f"nav2 map {path}:{i}: {key.strip()}: {exc}") from None
    return entries


def _number(path: Path, entries: dict[str, tuple[int, str | list[str]]], key: str) -> float:
    if key not in entries:
        raise OctolgpError(f"nav2 map {path}: no '{key}'")
    line, value = entries[key]
    try:
        number = float(value) if isinstance(value, str) else math.nan
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise OctolgpError(f"nav2 map {path}:{line}: {key} must be a number, got {value!r}")
    return number


def _read_pgm(path: Path) -> NDArray[np.float64]:
    """A binary PGM (``P5``, maxval <= 255) as shades ``(rows, cols)`` in [0, 1], row 0 on top."""
    if not path.is_file():
        raise MapFileNotFound(f"nav2 map image {str(path)!r} does not exist")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OctolgpError(f"PGM {path}: unreadable: {exc}") from None
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:  # magic, width, height, maxval; '#' comments to the end of line
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos : pos + 1] == b"#":
            pos = data.find(b"\n", pos) + 1 or len(data)
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            raise OctolgpError(f"PGM {path}: byte {pos}: truncated header")
        tokens.append(data[start:pos])
    pos += 1  # the single whitespace after maxval
    if tokens[0] != b"P5":
        raise OctolgpError(f"PGM {path}: byte 0: not a binary PGM (P5), got {tokens[0][:8]!r}")
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError:
        raise OctolgpError(f"PGM {path}: header: width, height, maxval must be integers") from None
    if width < 1 or height < 1 or not 0 < maxval <= 255:
        raise OctolgpError(f"PGM {path}: header: need width, height >= 1 and 0 < maxval <= 255")
    if len(data) - pos < width * height:
        raise OctolgpError(
            f"PGM {path}: byte {len(data)}: truncated: {len(data) - pos} of {width * height} pixels"
        )
    pixels = np.frombuffer(data, dtype=np.uint8, count=width * height, offset=pos)
    return np.asarray(pixels.reshape(height, width) / maxval, dtype=np.float64)


def read_nav2_map(path: PathLike) -> Nav2Map:
    """Read a nav2 ``map_server`` map (YAML and PGM) into cell states, as ``map_server`` does.

    Each pixel's ``occ`` is ``1 - shade`` (``shade`` with ``negate``); trinary: occupied
    (100) if ``occ > occupied_thresh``, free (0) if ``occ < free_thresh``, else unknown (-1);
    scale mode maps the values in between linearly to ``rint(100 (occ - free_thresh) /
    (occupied_thresh - free_thresh))``, as nav2 does.

    Parameters
    ----------
    path : str or os.PathLike
        The YAML file; its ``image`` is relative to it (or absolute). Only binary PGM images
        are read.

    Returns
    -------
    Nav2Map

    Raises
    ------
    MapFileNotFound
        If the YAML or its image does not exist.
    OctolgpError
        On a malformed YAML line (``nav2 map path:line: why``), a missing or bad key, a mode
        other than trinary or scale, or a malformed PGM.
    """
    yaml = Path(path)
    if not yaml.is_file():
        raise MapFileNotFound(f"nav2 map {str(yaml)!r} does not exist")
    entries = _read_yaml(yaml)
    if "image" not in entries or not isinstance(entries["image"][1], str):
        raise OctolgpError(f"nav2 map {yaml}: no 'image'")
    image = yaml.parent / entries["image"][1]
    resolution = _number(yaml, entries, "resolution")
    if not resolution > 0:
        raise OctolgpError(f"nav2 map {yaml}:{entries['resolution'][0]}: resolution must be > 0")
    if "origin" not in entries:
        raise OctolgpError(f"nav2 map {yaml}: no 'origin'")
    line, origin = entries["origin"]
    try:
        ox, oy, yaw = (float(v) for v in origin)
    except ValueError:
        raise OctolgpError(
            f"nav2 map {yaml}:{line}: origin must be [x, y, yaw], got {origin!r}"
        ) from None
    occupied = _number(yaml, entries, "occupied_thresh")
    free = _number(yaml, entries, "free_thresh")
    if not 0.0 <= free < occupied <= 1.0:
        raise OctolgpError(
            f"nav2 map {yaml}: need 0 <= free_thresh < occupied_thresh <= 1, got {free}, {occupied}"
        )
    negate = _number(yaml, entries, "negate") != 0 if "negate" in entries else False
    line, mode = entries.get("mode", (0, "trinary"))
    if mode not in _MODES:
        raise OctolgpError(f"nav2 map {yaml}:{line}: mode must be one of {_MODES}, got {mode!r}")
    shade = _read_pgm(image)[::-1]  # row 0 = lowest y
    occ = shade if negate else 1.0 - shade
    cells = np.full(occ.shape, UNKNOWN, dtype=np.int8)
    if mode == "scale":
        scaled = np.rint(100.0 * (occ - free) / (occupied - free))
        cells = np.clip(scaled, 0, 100).astype(np.int8)
    cells[occ > occupied] = OCCUPIED
    cells[occ < free] = FREE
    return Nav2Map(cells, resolution, (ox, oy, yaw), image, str(mode), negate, occupied, free)
