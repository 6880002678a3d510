"""Reading OctoMap files: the text header of ``.bt``/``.ot`` and a reference ``.bt`` decoder.

The formats are described in :mod:`octolgp.export.octomap`, which writes them.
"""

from __future__ import annotations

import math
import os
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray

from octolgp.errors import OctolgpError
from octolgp.export.common import PathLike
from octolgp.export.octomap import BT_HEADER, OT_HEADER
from octolgp.export.octree import CENTER, DEPTH, INNER, OCCUPIED, IntArray
from octolgp.geometry.keys import addressable_range

_MAX_EXPANDED = 50_000_000  # decode_bt(expand=True) refuses larger outputs


class OctomapHeader(TypedDict):
    """The text header of an OctoMap file, as :func:`read_bt_header` returns it."""

    kind: str  # "bt" (binary) or "ot" (full), from the first line
    id: str  # tree type, "OcTree"
    size: int  # nodes in the tree, root and inner nodes included
    res: float  # resolution, metres
    data_offset: int  # byte offset of the node data


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
        Depth of the tree whose keys to return, 1..16 (as in
        :func:`octolgp.export.octomap.write_bt`).
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
            if pos + 2 > len(data) or depth >= DEPTH:
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
                if state == INNER:
                    inner_children.append(child)
                else:
                    prefixes.append(child[1:])
                    states.append(state == OCCUPIED)
                    depths.append(child[0])
            stack.extend(reversed(inner_children))  # child 0 is read first
    if pos != len(data) or nodes != header["size"]:
        raise OctolgpError(
            f"{os.fspath(path)!r} is corrupt: {nodes} nodes in {pos} of {len(data)} data bytes, "
            f"header size {header['size']}"
        )
    depth_arr = np.asarray(depths, dtype=np.int64)
    occ = np.asarray(states, dtype=bool)
    span = np.left_shift(1, DEPTH - depth_arr)
    corner = np.asarray(prefixes, dtype=np.int64).reshape(-1, 3) * span[:, None]
    if expand:
        counts = span**3
        if counts.sum() > _MAX_EXPANDED:
            raise OctolgpError(f"expanding {os.fspath(path)!r} gives {counts.sum()} voxels")
        leaf = np.repeat(np.arange(span.size), counts)
        offset = np.arange(leaf.size) - np.repeat(np.cumsum(counts) - counts, counts)
        s = span[leaf]
        corner = corner[leaf] + np.column_stack([offset % s, offset // s % s, offset // (s * s)])
        occ, depth_arr = occ[leaf], np.full(leaf.size, DEPTH, dtype=np.int64)
    keys = corner - (CENTER - (1 << (tree_depth - 1)))
    if keys.size and (keys.min() < 0 or keys.max() >= (1 << tree_depth)):
        raise OctolgpError(f"{os.fspath(path)!r} has leaves outside a depth-{tree_depth} tree")
    return keys, occ, depth_arr
