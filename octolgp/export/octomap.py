"""Map export: OctoMap ``.bt`` and ``.ot`` files, PLY point clouds and PNG images.

OctoMap files
-------------
Both formats hold OctoMap's ``OcTree`` (``OcTreeBaseImpl`` and
``OccupancyOcTreeBase`` in ``OctoMap/octomap``, version 1.10): a 16-level tree whose
children are ordered ``x + 2 y + 4 z`` (see :func:`octolgp.geometry.keys.child_index`). The
text header is the one ``AbstractOccupancyOcTree::writeBinaryConst`` and
``AbstractOcTree::write`` print::

    # Octomap OcTree binary file          (.ot: "# Octomap OcTree file")
    # (feel free to add / change comments, but leave the first line as it is!)
    #
    id OcTree
    size <number of nodes, root and inner nodes included>
    res <resolution>
    data

followed by the nodes, depth first, children in order 0..7:

- ``.bt`` (``writeBinaryNode``): two bytes per *inner* node, ``child1to4`` then
  ``child5to8``; child ``i`` owns bits ``2 (i mod 4)`` and ``2 (i mod 4) + 1``:
  both clear for an unknown (absent) child, the low bit for a free leaf, the high
  bit for an occupied leaf and both for an inner node. Leaves carry no bytes.
- ``.ot`` (``writeNodesRecurs``): per node, its value (a little-endian float32
  log-odds) then one byte with bit ``i`` set when child ``i`` exists. An inner
  node's value is the maximum of its children's (``updateOccupancyChildren``).

OctoMap's readers check ``size`` against the nodes they build
(``calcNumNodes``), so the count must include every node. The trees are written
pruned as OctoMap's ``prune()`` leaves them: a node whose eight children are all
leaves with equal values (in ``.bt``, equal states) is itself a leaf, from the
bottom up; the root is never collapsed.

The tree is built bottom up, one vectorised pass per level, on Morton codes of
the keys; the depth-first order is a sort of ``(code << 3 (16 - depth), depth)``.
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import KEY_BITS, addressable_range, coord_to_key

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]
PathLike = str | os.PathLike[str]

BT_HEADER = "# Octomap OcTree binary file"
"""First line of a ``.bt`` file (``AbstractOccupancyOcTree::binaryFileHeader``)."""

OT_HEADER = "# Octomap OcTree file"
"""First line of a ``.ot`` file (``AbstractOcTree::fileHeader``)."""

_COMMENT = "# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
_DEPTH = KEY_BITS  # OctoMap's OcTree always has 16 levels below the root
_CENTER = 1 << (_DEPTH - 1)  # OctoMap's tree_max_val: the key of coordinate 0
_FREE, _OCCUPIED, _INNER = 1, 2, 3  # 2-bit child states of the .bt format
_OT_NODE = np.dtype([("value", "<f4"), ("children", "u1")])  # 5 bytes, unpadded
_MAX_EXPANDED = 50_000_000  # decode_bt(expand=True) refuses larger outputs


class OctomapHeader(TypedDict):
    """The text header of an OctoMap file, as :func:`read_bt_header` returns it."""

    kind: str  # "bt" (binary) or "ot" (full), from the first line
    id: str  # tree type, "OcTree"
    size: int  # nodes in the tree, root and inner nodes included
    res: float  # resolution, metres
    data_offset: int  # byte offset of the node data


# --- validation ----------------------------------------------------------------


def _keys16(keys: ArrayLike, tree_depth: int) -> IntArray:
    """Validate ``(k, 3)`` or 2D ``(k, 2)`` keys of a depth-``tree_depth`` tree; return 16-bit keys.

    2D keys get the z key of ``z in [0, resolution)``. Keys of a shallower tree are
    shifted so that they address the same coordinates in OctoMap's depth-16 tree.
    """
    k = np.asarray(keys)
    if k.dtype.kind not in "iu":
        raise OctolgpError(f"keys must be an integer array, got dtype {k.dtype}")
    if k.ndim != 2 or k.shape[1] not in (2, 3):
        raise OctolgpError(f"keys must have shape (k, 3) or (k, 2), got {k.shape}")
    limit = 1 << tree_depth
    if k.size and (k.min() < 0 or k.max() >= limit):
        raise OctolgpError(f"keys must lie in [0, {limit}), got [{k.min()}, {k.max()}]")
    shift = _CENTER - (1 << (tree_depth - 1))
    k16 = k.astype(np.int64) + shift
    if k16.shape[1] == 2:
        k16 = np.column_stack([k16, np.full(k16.shape[0], _CENTER, dtype=np.int64)])
    return k16


def _per_voxel(values: ArrayLike, count: int, name: str) -> NDArray[Any]:
    """Return ``values`` as a ``(count,)`` array, or raise naming ``name``."""
    v = np.asarray(values)
    if v.shape != (count,):
        raise OctolgpError(f"{name} must have shape ({count},), one per key, got {v.shape}")
    return v


def _as_occupied(occupied: ArrayLike, count: int) -> NDArray[np.bool_]:
    v = _per_voxel(occupied, count, "occupied")
    if v.dtype.kind == "b":
        return v
    if v.dtype.kind in "iu" and np.isin(v, (0, 1)).all():
        return v.astype(bool)
    raise OctolgpError(f"occupied must be boolean (or 0/1), got dtype {v.dtype}")


def _as_finite(values: ArrayLike, count: int, name: str) -> FloatArray:
    v = _per_voxel(values, count, name)
    if v.dtype.kind not in "biuf":
        raise OctolgpError(f"{name} must be real numbers, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise OctolgpError(f"{name} must be finite, got {int((~np.isfinite(v)).sum())} bad values")
    return v


def _as_centres(centres: ArrayLike, dims: tuple[int, ...]) -> FloatArray:
    c = np.asarray(centres)
    if c.ndim != 2 or c.shape[1] not in dims or c.dtype.kind not in "biuf":
        raise OctolgpError(f"centres must be a real array of shape (k, {dims}), got {c.shape}")
    c = c.astype(np.float64)
    if not np.isfinite(c).all():
        raise OctolgpError("centres must be finite")
    return c


def _as_prob(prob: ArrayLike, count: int) -> FloatArray:
    p = _as_finite(prob, count, "prob")
    if p.size and (p.min() < 0.0 or p.max() > 1.0):
        raise OctolgpError(f"prob must lie in [0, 1], got [{p.min():g}, {p.max():g}]")
    return p


def _write_bytes(path: PathLike, chunks: list[bytes]) -> None:
    """Write ``chunks`` to ``path``; an OS failure raises :class:`OctolgpError`."""
    try:
        with open(path, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
    except OSError as exc:
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be written: {exc}") from exc


# --- Morton codes ----------------------------------------------------------------


def _spread3(v: IntArray) -> IntArray:
    """Spread the 16 low bits of ``v`` to every third bit (bit ``i`` to bit ``3 i``)."""
    v = v & 0xFFFF
    v = (v | (v << 16)) & 0x0000_FF00_00FF
    v = (v | (v << 8)) & 0x00F0_0F00_F00F
    v = (v | (v << 4)) & 0x0C30_C30C_30C3
    v = (v | (v << 2)) & 0x2492_4924_9249
    return v


def _compact3(v: IntArray) -> IntArray:
    """Invert :func:`_spread3`: gather every third bit into the 16 low bits."""
    v = v & 0x2492_4924_9249
    v = (v | (v >> 2)) & 0x0C30_C30C_30C3
    v = (v | (v >> 4)) & 0x00F0_0F00_F00F
    v = (v | (v >> 8)) & 0x0000_FF00_00FF
    v = (v | (v >> 16)) & 0xFFFF
    return v


def _morton(keys16: IntArray) -> IntArray:
    """Interleave key bits so that bits ``3 l .. 3 l + 2`` are the child index at level ``l``."""
    code: IntArray = (
        _spread3(keys16[:, 0]) | (_spread3(keys16[:, 1]) << 1) | (_spread3(keys16[:, 2]) << 2)
    )
    return code


def _unmorton(code: IntArray) -> IntArray:
    return np.column_stack([_compact3(code), _compact3(code >> 1), _compact3(code >> 2)])


# --- the pruned tree, bottom up ------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Level:
    """The nodes at one depth, sorted by Morton prefix."""

    code: IntArray  # Morton prefix, 3 bits per level above
    value: NDArray[np.float32]  # leaf value, or the maximum of the children
    inner: NDArray[np.bool_]
    children: NDArray[np.uint8]  # .ot child bitmask, 0 for leaves
    states: NDArray[np.uint16]  # .bt 2-bit child states, 0 for leaves


def _build_tree(keys16: IntArray, values: NDArray[np.float32]) -> list[_Level]:
    """Build the pruned tree over leaf voxels; ``levels[d]`` holds the nodes at depth ``d``.

    A leaf's .bt state is occupied when its value is positive. Raises on duplicate keys.
    """
    code = _morton(keys16)
    order = np.argsort(code)
    code, values = code[order], values[order]
    if code.size > 1 and (code[1:] == code[:-1]).any():
        raise OctolgpError("keys must be unique, got duplicate voxels")
    n = code.size
    levels = [
        _Level(code, values, np.zeros(n, bool), np.zeros(n, np.uint8), np.zeros(n, np.uint16))
    ]
    for depth in range(_DEPTH, 0, -1):
        nodes = levels[-1]
        # Group the nodes of this depth by parent (codes are sorted, so groups are runs).
        slot = (nodes.code & 7).astype(np.int64)
        parent = nodes.code >> 3
        first = np.ones(parent.size, bool)
        first[1:] = parent[1:] != parent[:-1]
        starts = np.flatnonzero(first)
        n_children = np.diff(np.append(starts, parent.size))
        state = np.where(nodes.inner, _INNER, np.where(nodes.value > 0, _OCCUPIED, _FREE))
        children = np.bitwise_or.reduceat((1 << slot).astype(np.uint8), starts)
        states = np.bitwise_or.reduceat((state << (2 * slot)).astype(np.uint16), starts)
        high = np.maximum.reduceat(nodes.value, starts)
        low = np.minimum.reduceat(nodes.value, starts)
        any_inner = np.logical_or.reduceat(nodes.inner, starts)
        # OcTreeBaseImpl::isNodeCollapsible: eight leaf children of equal value (never the root).
        collapse = (n_children == 8) & ~any_inner & (high == low) & (depth > 1)
        if collapse.any():
            keep = ~np.repeat(collapse, n_children)
            levels[-1] = _Level(
                nodes.code[keep],
                nodes.value[keep],
                nodes.inner[keep],
                nodes.children[keep],
                nodes.states[keep],
            )
        levels.append(
            _Level(
                parent[starts],
                high,
                ~collapse,
                np.where(collapse, 0, children).astype(np.uint8),
                np.where(collapse, 0, states).astype(np.uint16),
            )
        )
    levels.reverse()
    return levels


def _depth_first(levels: list[_Level], inner_only: bool) -> NDArray[np.int64]:
    """Return the permutation putting the levels' nodes (concatenated) in depth-first order.

    A node's first descendant leaf has the node's code padded to depth 16; sorting on
    ``(padded code, depth)`` puts every node right before its subtree (pre-order).
    """
    sort_keys = []
    for depth, level in enumerate(levels):
        code = level.code[level.inner] if inner_only else level.code
        sort_keys.append((code << (3 * (_DEPTH - depth))) << 5 | depth)
    order: NDArray[np.int64] = np.argsort(np.concatenate(sort_keys))
    return order


def _header(first_line: str, size: int, resolution: float) -> bytes:
    return (
        f"{first_line}\n{_COMMENT}id OcTree\nsize {size}\nres {float(resolution)!r}\ndata\n"
    ).encode("ascii")


def _check_tree_args(resolution: float, tree_depth: int) -> None:
    addressable_range(resolution, tree_depth)  # raises on a bad resolution or depth


def write_bt(
    path: PathLike,
    keys: ArrayLike,
    occupied: ArrayLike,
    resolution: float,
    tree_depth: int = 16,
) -> int:
    """Write known voxels as an OctoMap binary (max-likelihood) ``.bt`` file.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    keys : array_like of int, shape (k, 3) or (k, 2)
        Unique OctoMap keys of the known voxels in a tree of depth ``tree_depth``
        (``floor(x / resolution) + 2**(tree_depth - 1)`` per axis). 2D keys are
        written as one layer covering ``z in [0, resolution)`` (z key 32768 in the
        file).
    occupied : array_like of bool, shape (k,)
        True for occupied, False for free voxels.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Depth of the tree ``keys`` belong to, 1..16. The file always holds OctoMap's
        16-level tree, so keys of a shallower tree are re-centred to the same
        coordinates.

    Returns
    -------
    int
        Nodes in the written tree, root and inner nodes included: the header's
        ``size``, which OctoMap's ``OcTree::size()`` reports after reading. 0 for
        no voxels (a header with ``size 0`` and no data, as OctoMap writes an
        empty tree).

    Raises
    ------
    OctolgpError
        On bad or duplicate ``keys``, a bad ``occupied``, ``resolution`` or
        ``tree_depth``, or a ``path`` that cannot be written.
    """
    _check_tree_args(resolution, tree_depth)
    keys16 = _keys16(keys, tree_depth)
    occ = _as_occupied(occupied, keys16.shape[0])
    if keys16.shape[0] == 0:
        _write_bytes(path, [_header(BT_HEADER, 0, resolution)])
        return 0
    levels = _build_tree(keys16, np.where(occ, 1.0, -1.0).astype(np.float32))
    order = _depth_first(levels, inner_only=True)
    states = np.concatenate([level.states[level.inner] for level in levels])[order]
    size = sum(level.code.size for level in levels)
    # Low byte child1to4, high byte child5to8: little-endian uint16.
    _write_bytes(path, [_header(BT_HEADER, size, resolution), states.astype("<u2").tobytes()])
    return size


def write_ot(
    path: PathLike,
    keys: ArrayLike,
    log_odds: ArrayLike,
    resolution: float,
    tree_depth: int = 16,
) -> int:
    """Write known voxels with their log-odds as an OctoMap full ``.ot`` file.

    Inner nodes hold the maximum of their children (OctoMap's
    ``updateInnerOccupancy``); eight leaf children with equal float32 values are
    pruned into their parent.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    keys : array_like of int, shape (k, 3) or (k, 2)
        Unique OctoMap keys, as in :func:`write_bt`.
    log_odds : array_like of float, shape (k,)
        Occupancy log-odds ``log(p / (1 - p))`` per voxel, stored as float32.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Depth of the tree ``keys`` belong to, as in :func:`write_bt`.

    Returns
    -------
    int
        Nodes written (the header's ``size``; 0 for no voxels).

    Raises
    ------
    OctolgpError
        On bad or duplicate ``keys``, a non-finite ``log_odds``, a bad
        ``resolution`` or ``tree_depth``, or a ``path`` that cannot be written.
    """
    _check_tree_args(resolution, tree_depth)
    keys16 = _keys16(keys, tree_depth)
    log_odds64 = _as_finite(log_odds, keys16.shape[0], "log_odds")
    if log_odds64.size and np.abs(log_odds64).max() > np.finfo(np.float32).max:
        raise OctolgpError("log_odds must fit in float32")
    values = log_odds64.astype(np.float32)
    if keys16.shape[0] == 0:
        _write_bytes(path, [_header(OT_HEADER, 0, resolution)])
        return 0
    levels = _build_tree(keys16, values)
    order = _depth_first(levels, inner_only=False)
    nodes = np.empty(order.size, dtype=_OT_NODE)
    nodes["value"] = np.concatenate([level.value for level in levels])[order]
    nodes["children"] = np.concatenate([level.children for level in levels])[order]
    _write_bytes(path, [_header(OT_HEADER, order.size, resolution), nodes.tobytes()])
    return int(order.size)


# --- reading ----------------------------------------------------------------------


def _read_file(path: PathLike) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as exc:
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be read: {exc}") from exc


def _parse_header(blob: bytes, path: PathLike) -> OctomapHeader:
    """Parse OctoMap's text header as ``AbstractOcTree::readHeader`` does (line by line)."""
    where = os.fspath(path)
    first_end = blob.find(b"\n")
    first = blob[: max(first_end, 0)].decode("ascii", "replace")
    if first.startswith(BT_HEADER):
        kind = "bt"
    elif first.startswith(OT_HEADER):
        kind = "ot"
    else:
        raise OctolgpError(f"{where!r} is not an OctoMap file: first line {first[:40]!r}")
    fields: dict[str, str] = {}
    pos = first_end + 1
    while True:
        end = blob.find(b"\n", pos)
        if end < 0:
            raise OctolgpError(f"{where!r} has no 'data' line in its OctoMap header")
        tokens = blob[pos:end].decode("ascii", "replace").split()
        pos = end + 1
        if not tokens or tokens[0].startswith("#"):
            continue
        if tokens[0] == "data":
            break
        if tokens[0] in ("id", "size", "res") and len(tokens) >= 2:
            fields[tokens[0]] = tokens[1]
    try:
        header = OctomapHeader(
            kind=kind,
            id=fields["id"],
            size=int(fields["size"]),
            res=float(fields["res"]),
            data_offset=pos,
        )
    except (KeyError, ValueError) as exc:
        raise OctolgpError(f"{where!r} has a bad OctoMap header: {exc}") from exc
    if header["size"] < 0 or not header["res"] > 0.0 or not math.isfinite(header["res"]):
        raise OctolgpError(f"{where!r} has a bad OctoMap header: size or res out of range")
    return header


def read_bt_header(path: PathLike) -> OctomapHeader:
    """Read the text header of an OctoMap ``.bt`` (or ``.ot``) file.

    Parameters
    ----------
    path : str or os.PathLike
        An OctoMap file.

    Returns
    -------
    OctomapHeader
        A dict: ``kind`` (``"bt"`` or ``"ot"``, from the first line), ``id`` (the tree
        type, ``"OcTree"``), ``size`` (node count), ``res`` (resolution, metres)
        and ``data_offset`` (byte offset of the node data).

    Raises
    ------
    OctolgpError
        On an unreadable file or a header that is not OctoMap's.
    """
    return _parse_header(_read_file(path), path)


def decode_bt(
    path: PathLike, tree_depth: int = 16, *, expand: bool = False
) -> tuple[IntArray, NDArray[np.bool_], IntArray]:
    """Decode the leaves of a ``.bt`` file (a pure-Python reference reader).

    Walks the node bytes depth first with an explicit stack, as OctoMap's
    ``readBinaryNode`` recurses; meant for tests on small maps.

    Parameters
    ----------
    path : str or os.PathLike
        An OctoMap ``.bt`` file.
    tree_depth : int, optional
        Depth of the tree whose keys to return, 1..16 (as in :func:`write_bt`).
    expand : bool, optional
        Return every depth-16 voxel covered by a coarser (pruned) leaf instead of
        one row per leaf.

    Returns
    -------
    keys : ndarray of int64, shape (k, 3)
        Per leaf, the key of its lowest corner voxel, in the ``tree_depth``
        convention; sorted in file (depth-first) order.
    occupied : ndarray of bool, shape (k,)
        The leaf's state.
    depth : ndarray of int64, shape (k,)
        The leaf's depth in OctoMap's 16-level tree (16 for a voxel; a leaf at
        depth ``t`` spans ``2**(16 - t)`` voxels per axis). All 16 with ``expand``.

    Raises
    ------
    OctolgpError
        On an unreadable, foreign or corrupt file, a node count that disagrees
        with the header, a leaf outside the ``tree_depth`` range, or an expansion
        of more than 50 million voxels.
    """
    addressable_range(1.0, tree_depth)  # validates tree_depth
    blob = _read_file(path)
    header = _parse_header(blob, path)
    if header["kind"] != "bt":
        raise OctolgpError(f"{os.fspath(path)!r} is not a binary (.bt) OctoMap file")
    data = memoryview(blob)[header["data_offset"] :]
    prefixes: list[tuple[int, int, int]] = []
    states: list[bool] = []
    depths: list[int] = []
    nodes, pos = 0, 0
    if header["size"] > 0:
        nodes = 1
        stack: list[tuple[int, int, int, int]] = [(0, 0, 0, 0)]  # depth, x, y, z prefixes
        while stack:
            depth, x, y, z = stack.pop()
            if pos + 2 > len(data) or depth >= _DEPTH:
                raise OctolgpError(f"{os.fspath(path)!r} has truncated or too deep .bt data")
            code = data[pos] | (data[pos + 1] << 8)
            pos += 2
            inner_children = []
            for i in range(8):
                state = (code >> (2 * i)) & 3
                if state == 0:
                    continue
                nodes += 1
                child = (depth + 1, x << 1 | (i & 1), y << 1 | (i >> 1 & 1), z << 1 | (i >> 2))
                if state == _INNER:
                    inner_children.append(child)
                else:
                    prefixes.append(child[1:])
                    states.append(state == _OCCUPIED)
                    depths.append(child[0])
            stack.extend(reversed(inner_children))  # child 0 is read first
    if pos != len(data) or nodes != header["size"]:
        raise OctolgpError(
            f"{os.fspath(path)!r} is corrupt: {nodes} nodes in {pos} of {len(data)} data bytes, "
            f"header size {header['size']}"
        )
    depth_arr = np.asarray(depths, dtype=np.int64)
    occ = np.asarray(states, dtype=bool)
    span = np.left_shift(1, _DEPTH - depth_arr)
    corner = np.asarray(prefixes, dtype=np.int64).reshape(-1, 3) * span[:, None]
    if expand:
        counts = span**3
        if counts.sum() > _MAX_EXPANDED:
            raise OctolgpError(f"expanding {os.fspath(path)!r} gives {counts.sum()} voxels")
        leaf = np.repeat(np.arange(span.size), counts)
        offset = np.arange(leaf.size) - np.repeat(np.cumsum(counts) - counts, counts)
        s = span[leaf]
        corner = corner[leaf] + np.column_stack([offset % s, offset // s % s, offset // (s * s)])
        occ, depth_arr = occ[leaf], np.full(leaf.size, _DEPTH, dtype=np.int64)
    keys = corner - (_CENTER - (1 << (tree_depth - 1)))
    if keys.size and (keys.min() < 0 or keys.max() >= (1 << tree_depth)):
        raise OctolgpError(f"{os.fspath(path)!r} has leaves outside a depth-{tree_depth} tree")
    return keys, occ, depth_arr


# --- point clouds and images --------------------------------------------------------


def write_ply(path: PathLike, centres: ArrayLike, prob: ArrayLike, *, binary: bool = True) -> None:
    """Write voxel centres and their occupancy probability as a PLY point cloud.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    centres : array_like of float, shape (k, 3) or (k, 2)
        Voxel centres in the world frame, metres; 2D centres get ``z = 0``.
    prob : array_like of float, shape (k,)
        P(occupied) per centre, in [0, 1].
    binary : bool, optional
        ``binary_little_endian`` (default) or ``ascii`` PLY. Either way the vertex
        has float32 properties ``x y z prob``.

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value in ``centres`` or ``prob``, ``prob``
        outside [0, 1], or a ``path`` that cannot be written.
    """
    c = _as_centres(centres, (2, 3))
    p = _as_prob(prob, c.shape[0])
    if c.shape[1] == 2:
        c = np.column_stack([c, np.zeros(c.shape[0])])
    vertex = np.empty(c.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("prob", "<f4")])
    for axis, name in enumerate("xyz"):
        vertex[name] = c[:, axis]
    vertex["prob"] = p
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment octolgp occupancy\nelement vertex {c.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float prob\nend_header\n"
    ).encode("ascii")
    if binary:
        body = vertex.tobytes()
    else:
        text = io.StringIO()
        rows = np.column_stack([vertex[name] for name in ("x", "y", "z", "prob")])
        np.savetxt(text, rows, fmt="%.9g")  # 9 significant digits round-trip float32
        body = text.getvalue().encode("ascii")
    _write_bytes(path, [header, body])


def write_png(
    path: PathLike,
    centres: ArrayLike,
    prob: ArrayLike,
    resolution: float,
    *,
    dpi: int = 100,
) -> None:
    """Draw a 2D occupancy image: occupied dark, free light, unknown mid-grey.

    The cells form a grid of pitch ``resolution`` over the centres' bounding box;
    cells without a centre are unknown (P = 0.5). The axes show world x and y in
    metres. Uses Matplotlib's object API (``matplotlib.figure.Figure``), so no
    global backend or pyplot state is touched.

    Parameters
    ----------
    path : str or os.PathLike
        Output image; the format follows the extension (``.png``).
    centres : array_like of float, shape (k, 2)
        Cell centres in the world frame, metres.
    prob : array_like of float, shape (k,)
        P(occupied) per cell, in [0, 1].
    resolution : float
        Cell edge, metres.
    dpi : int, optional
        Image resolution in dots per inch.

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value in ``centres`` or ``prob``, no cells,
        a bad ``resolution``, or a ``path`` that cannot be written.
    """
    _check_tree_args(resolution, 16)
    c = _as_centres(centres, (2,))
    p = _as_prob(prob, c.shape[0])
    if c.shape[0] == 0:
        raise OctolgpError("centres must hold at least one cell to draw")
    low = c.min(axis=0)
    cell = np.rint((c - low) / resolution).astype(np.int64)
    nx, ny = (cell.max(axis=0) + 1).tolist()
    if nx * ny > 100_000_000:
        raise OctolgpError(f"centres span {nx} x {ny} cells at resolution {resolution:g}")
    grid = np.full((ny, nx), 0.5)
    grid[cell[:, 1], cell[:, 0]] = p
    half = 0.5 * resolution
    extent = (
        low[0] - half,
        low[0] + (nx - 0.5) * resolution,
        low[1] - half,
        low[1] + (ny - 0.5) * resolution,
    )

    from matplotlib.figure import Figure  # lazy: keeps `import octolgp` light

    width = 8.0
    fig = Figure(
        figsize=(width, max(2.0, min(3 * width, width * ny / nx))), dpi=dpi, layout="constrained"
    )
    ax = fig.add_subplot()
    image = ax.imshow(
        grid,
        origin="lower",
        extent=extent,
        cmap="gray_r",
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.colorbar(image, ax=ax, label="P(occupied)")
    try:
        fig.savefig(os.fspath(path), dpi=dpi)
    except OSError as exc:
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be written: {exc}") from exc


def write_map_voxels(
    path: PathLike,
    centres: FloatArray,
    prob: FloatArray,
    resolution: float,
    tree_depth: int,
    threshold: float = 0.5,
) -> int:
    """Write predicted voxels as an OctoMap file, chosen by suffix.

    ``.ot``: each voxel's log-odds ``log(P / (1 − P))`` (P clipped to
    ``[1e-6, 1 − 1e-6]``). Otherwise ``.bt``: occupied where ``P > threshold``.

    Parameters
    ----------
    path : str or Path
    centres : ndarray of shape (k, d)
        Voxel centres, metres, world frame (a 2D map is one layer at z key 32768).
    prob : ndarray of shape (k,)
        P(occupied).
    resolution : float
    tree_depth : int
    threshold : float

    Returns
    -------
    int
        Nodes written.
    """
    keys = coord_to_key(centres, resolution, tree_depth)
    p = Path(path)
    if p.suffix == ".ot":
        q = np.clip(prob, 1e-6, 1.0 - 1e-6)
        return write_ot(p, keys, np.log(q / (1.0 - q)), resolution)
    return write_bt(p, keys, prob > threshold, resolution)
