"""OctoMap ``.bt`` and ``.ot`` files: the writers.

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
bottom up; the root is never collapsed. The tree itself is built in
:mod:`octolgp.export.octree`; :mod:`octolgp.export.octomap_read` reads the files back.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.export.common import FloatArray, PathLike, as_finite, per_voxel, write_bytes
from octolgp.export.octree import (
    DEPTH,
    IntArray,
    Level,
    build_tree,
    depth_first,
    grow_tree,
    to_keys16,
)
from octolgp.geometry.keys import addressable_range, coord_to_key

BT_HEADER = "# Octomap OcTree binary file"
"""First line of a ``.bt`` file (``AbstractOccupancyOcTree::binaryFileHeader``)."""

OT_HEADER = "# Octomap OcTree file"
"""First line of a ``.ot`` file (``AbstractOcTree::fileHeader``)."""

_COMMENT = "# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
_OT_NODE = np.dtype([("value", "<f4"), ("children", "u1")])  # 5 bytes, unpadded
_FIELDS = ("value", "inner", "children", "states")  # a Level's arrays beside its codes


def _as_occupied(occupied: ArrayLike, count: int) -> NDArray[np.bool_]:
    v = per_voxel(occupied, count, "occupied")
    if v.dtype.kind == "b":
        return v
    if v.dtype.kind in "iu" and np.isin(v, (0, 1)).all():
        return v.astype(bool)
    raise OctolgpError(f"occupied must be boolean (or 0/1), got dtype {v.dtype}")


def _log_odds32(log_odds: ArrayLike, count: int) -> NDArray[np.float32]:
    """Per-voxel log-odds as float32 (raises on a non-finite one or one beyond float32)."""
    v = as_finite(log_odds, count, "log_odds")
    if v.size and np.abs(v).max() > np.finfo(np.float32).max:
        raise OctolgpError("log_odds must fit in float32")
    return v.astype(np.float32)


def _header(first_line: str, size: int, resolution: float) -> bytes:
    return (
        f"{first_line}\n{_COMMENT}id OcTree\nsize {size}\nres {float(resolution)!r}\ndata\n"
    ).encode("ascii")


def _check_tree_args(resolution: float, tree_depth: int) -> None:
    addressable_range(resolution, tree_depth)  # raises on a bad resolution or depth


def bt_data(
    keys: ArrayLike,
    occupied: ArrayLike,
    resolution: float,
    tree_depth: int = 16,
) -> tuple[bytes, int]:
    """The node stream of a ``.bt`` file: OctoMap's ``writeBinaryData``, without the header.

    This is what follows ``data`` in a ``.bt`` file and what ``octomap_msgs/Octomap``
    carries in ``data`` when ``binary`` is true (``octomap_msgs::binaryMapToMsg``).

    Parameters
    ----------
    keys, occupied, resolution, tree_depth
        As :func:`write_bt`.

    Returns
    -------
    data : bytes
        Two bytes per inner node, depth first (empty for no voxels).
    size : int
        Nodes in the tree, root and inner nodes included (0 for no voxels).

    Raises
    ------
    OctolgpError
        On bad or duplicate ``keys``, a bad ``occupied``, ``resolution`` or ``tree_depth``.
    """
    _check_tree_args(resolution, tree_depth)
    keys16 = to_keys16(keys, tree_depth)
    occ = _as_occupied(occupied, keys16.shape[0])
    if keys16.shape[0] == 0:
        return b"", 0
    levels = build_tree(keys16, np.where(occ, 1.0, -1.0).astype(np.float32))
    order = depth_first(levels, inner_only=True)
    states = np.concatenate([level.states[level.inner] for level in levels])[order]
    size = sum(level.code.size for level in levels)
    # Low byte child1to4, high byte child5to8: little-endian uint16.
    return states.astype("<u2").tobytes(), int(size)


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
    data, size = bt_data(keys, occupied, resolution, tree_depth)
    write_bytes(path, [_header(BT_HEADER, size, resolution), data])
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
    keys16 = to_keys16(keys, tree_depth)
    values = _log_odds32(log_odds, keys16.shape[0])
    if keys16.shape[0] == 0:
        write_bytes(path, [_header(OT_HEADER, 0, resolution)])
        return 0
    levels = build_tree(keys16, values)
    order = depth_first(levels, inner_only=False)
    nodes = np.empty(order.size, dtype=_OT_NODE)
    nodes["value"] = np.concatenate([level.value for level in levels])[order]
    nodes["children"] = np.concatenate([level.children for level in levels])[order]
    write_bytes(path, [_header(OT_HEADER, order.size, resolution), nodes.tobytes()])
    return int(order.size)


def write_tree_chunks(
    path: PathLike,
    chunks: Iterable[tuple[ArrayLike, ArrayLike]],
    resolution: float,
    tree_depth: int,
    split: int,
    *,
    full: bool,
) -> int:
    """Write a ``.bt`` (``full=False``) or ``.ot`` (``full=True``) file from chunks of voxels.

    Each chunk's subtrees below depth ``split`` of OctoMap's 16-level tree are built and
    serialised on their own, holding one chunk's voxels at a time; the tree above them
    is then built from the subtrees' roots (pruned as the whole tree would be) and the
    file is their pre-order. The bytes are those of :func:`write_bt` / :func:`write_ot`
    on every voxel at once; what is held is one chunk and the output's bytes.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    chunks : iterable of (keys, values)
        ``keys`` as :func:`write_bt`; ``values`` the voxels' occupied flags (``.bt``) or
        log-odds (``.ot``). Every voxel of a subtree at depth ``split`` is in one chunk.
    resolution : float
    tree_depth : int
        Depth of the tree the keys belong to.
    split : int
        The depth of the subtrees a chunk holds whole, 1..16 (for a map's chunks of
        whole leaves of ``2**s`` voxels on an edge: ``16 - s``).
    full : bool
        ``.ot`` when true, else ``.bt``.

    Returns
    -------
    int
        Nodes written (the header's ``size``; 0 for no voxels).

    Raises
    ------
    OctolgpError
        On bad or duplicate keys or values, a subtree split across chunks, a bad
        ``resolution``, ``tree_depth`` or ``split``, or a ``path`` that cannot be written.
    """
    _check_tree_args(resolution, tree_depth)
    if isinstance(split, bool) or not isinstance(split, int) or not 1 <= split <= DEPTH:
        raise OctolgpError(f"split must be an integer in 1..{DEPTH}, got {split!r}")
    record = 5 if full else 2  # .ot: value and child mask per node; .bt: states per inner node
    roots: list[Level] = []
    spans: list[IntArray] = []  # per root: its subtree's nodes and bytes
    streams: list[bytes] = []
    for keys, values in chunks:  # one chunk of voxels per iteration
        keys16 = to_keys16(keys, tree_depth)
        if full:
            v32 = _log_odds32(values, keys16.shape[0])
        else:
            v32 = np.where(_as_occupied(values, keys16.shape[0]), 1.0, -1.0).astype(np.float32)
        if keys16.shape[0] == 0:
            continue
        levels = build_tree(keys16, v32, top=split)
        order = depth_first(levels, inner_only=False, top=split)
        depth = np.repeat(np.arange(split, DEPTH + 1), [lv.code.size for lv in levels])[order]
        inner = np.concatenate([lv.inner for lv in levels])[order]
        if full:
            nodes = np.empty(order.size, dtype=_OT_NODE)
            nodes["value"] = np.concatenate([lv.value for lv in levels])[order]
            nodes["children"] = np.concatenate([lv.children for lv in levels])[order]
            streams.append(nodes.tobytes())
            node_bytes = np.full(order.size, record)
        else:
            states = np.concatenate([lv.states for lv in levels])[order]
            streams.append(states[inner].astype("<u2").tobytes())
            node_bytes = np.where(inner, record, 0)
        starts = np.flatnonzero(depth == split)  # each subtree begins with its root
        n_bytes = np.add.reduceat(node_bytes, starts)
        offset = np.cumsum(n_bytes) - n_bytes  # in this chunk's stream
        chunk = np.full(starts.size, len(streams) - 1)
        spans.append(np.column_stack([np.diff(np.r_[starts, order.size]), n_bytes, offset, chunk]))
        roots.append(levels[0])
    header = OT_HEADER if full else BT_HEADER
    if not roots:
        write_bytes(path, [_header(header, 0, resolution)])
        return 0
    code = np.concatenate([r.code for r in roots])
    by_code = np.argsort(code, kind="stable")
    code = code[by_code]
    if code.size > 1 and np.any(code[1:] == code[:-1]):
        raise OctolgpError(f"chunks must hold whole subtrees of depth {split}, got one split")
    span = np.concatenate(spans)[by_code]  # per root: nodes, bytes, offset, its chunk
    top = grow_tree(
        Level(code, *(np.concatenate([getattr(r, f) for r in roots])[by_code] for f in _FIELDS)),
        split,
        0,
    )  # top[d] at depth d; roots pruned into their parents are gone from top[split]
    kept = span[np.searchsorted(code, top[split].code)]
    counts = [lv.code.size for lv in top]
    size = sum(counts[:split]) + int(kept[:, 0].sum())
    order = depth_first(top, inner_only=False)
    depth = np.repeat(np.arange(split + 1), counts)[order]
    row = (order - np.repeat(np.cumsum([0, *counts[:-1]]), counts)[order]).tolist()
    above = [np.concatenate([getattr(lv, f) for lv in top[:split]]) for f in _FIELDS]
    at = (order[depth < split]).tolist()
    if full:  # every node above the split: its value and child mask
        nodes = np.empty(len(at), dtype=_OT_NODE)
        nodes["value"], nodes["children"] = above[0][at], above[2][at]
        records = [nodes[i : i + 1].tobytes() for i in range(len(at))]
    else:  # inner nodes only: their children's 2-bit states
        records = [
            int(state).to_bytes(2, "little") if inner else b""
            for state, inner in zip(above[3][at].tolist(), above[1][at].tolist(), strict=True)
        ]
    views = [memoryview(stream) for stream in streams]  # pieces of them, never copied
    pieces: list[bytes | memoryview] = [_header(header, size, resolution)]
    upper = iter(records)
    for d, r in zip(depth.tolist(), row, strict=True):  # one per node at or above the split
        if d < split:
            pieces.append(next(upper))
        else:
            pieces.append(views[kept[r, 3]][kept[r, 2] : kept[r, 2] + kept[r, 1]])
    write_bytes(path, pieces)
    return size


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
        return write_ot(p, keys, np.log(q / (1.0 - q)), resolution, tree_depth)
    return write_bt(p, keys, prob > threshold, resolution, tree_depth)


def write_map_voxel_chunks(
    path: PathLike,
    chunks: Iterable[tuple[FloatArray, FloatArray]],
    resolution: float,
    tree_depth: int,
    split: int,
    threshold: float = 0.5,
) -> int:
    """:func:`write_map_voxels` from chunks of voxels, one chunk held at a time.

    Parameters
    ----------
    path : str or Path
        ``.ot`` or, otherwise, ``.bt``.
    chunks : iterable of (centres, prob)
        Voxel centres, shape (k, d), metres, world frame, and P(occupied), shape (k,);
        every voxel of a subtree at depth ``split`` of OctoMap's tree in one chunk
        (for a map's chunks of whole leaves of ``2**s`` voxels a side: ``16 - s``).
    resolution, tree_depth, threshold
        As :func:`write_map_voxels`.
    split : int
        As :func:`write_tree_chunks`.

    Returns
    -------
    int
        Nodes written; the bytes are those of :func:`write_map_voxels` on the
        chunks concatenated.
    """
    full = Path(path).suffix == ".ot"

    def voxels() -> Iterable[tuple[ArrayLike, ArrayLike]]:
        for centres, prob in chunks:  # one chunk per iteration
            keys = coord_to_key(centres, resolution, tree_depth)
            if full:
                q = np.clip(prob, 1e-6, 1.0 - 1e-6)
                yield keys, np.log(q / (1.0 - q))
            else:
                yield keys, prob > threshold

    return write_tree_chunks(path, voxels(), resolution, tree_depth, split, full=full)
