"""The lattice engine's evidence as a compact record: what a leaf must keep to be refitted.

A lattice leaf's voxel values are a deterministic function of its evidence, so the map
file keeps the evidence only and a leaf read back is fitted again. The record, before
the map file compresses it:

- a header: halo-box voxels ``H`` (uint32), kept returns ``r`` (uint32), flags (uint8;
  bit 0: the returns' voxels are listed);
- a bitmap of the ``H`` halo-box voxels with a count (``np.packbits``, little bit order);
- the occupied counts, then the free counts, of those voxels (uint8 each);
- where flag 0 is set, each return's voxel as its flat index in the halo box (uint32);
  otherwise the returns are those of the occupied voxels in flat order, which is how a
  lattice leaf keeps them (one return per voxel with an occupied count, keys ascending);
- each return's cell inside its voxel, :data:`~octolgp.geometry.keys.RETURN_STEPS` per
  axis (uint16), one axis after the other; or, with flag bit 1 (returns of a leaf made
  before returns were kept at cells, from an older map file), their positions (float64);
- with flag bit 3, the summed chord shares of the voxels with a count (uint16 each,
  ``LatticeConfig.free_evidence = "chord"``; records without it keep none);
- with flag bit 2, a bitmap of the ``H`` halo-box voxels swept between beams
  (``np.packbits``, little bit order; records without it have none swept).

Kept returns are placed at their cells' centres when they are observed
(:func:`octolgp.geometry.keys.step_points`), so the record is exact: a leaf read back
holds the same evidence, bit for bit.
"""

from __future__ import annotations

import struct

import numpy as np
from numpy.typing import NDArray

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import pack_keys, return_steps, step_points, unpack_keys
from octolgp.mapping.grid import LeafGrid
from octolgp.training import IntArray

_HEAD = struct.Struct("<IIB")
_LISTED = 1  # flag: the returns' voxels are listed
_EXACT = 2  # flag: the returns' positions are stored as float64
_SWEPT = 4  # flag: a bitmap of the swept voxels ends the record
_CHORD = 8  # flag: the seen voxels' summed chord shares precede the swept bitmap


def _box_origin(index: IntArray, grid: LeafGrid) -> IntArray:
    """The voxel key of the lower corner of a leaf's halo box, per axis."""
    origin: IntArray = np.asarray(index, dtype=np.int64) * grid.side - grid.halo_voxels
    return origin


def encode_lattice(
    counts: np.ndarray,
    hit_keys: IntArray,
    hits: np.ndarray,
    index: IntArray,
    grid: LeafGrid,
    swept: np.ndarray | None = None,
    chord: np.ndarray | None = None,
) -> bytes:
    """The compact record of a lattice leaf's evidence (see the module's docstring).

    Parameters
    ----------
    counts : ndarray of uint8, shape (2, H)
        Occupied and free counts per halo-box voxel.
    hit_keys : ndarray of int64, shape (r,)
        Packed keys of the voxels holding a kept return, ascending.
    hits : ndarray of shape (r, d)
        The kept returns, metres, world frame, at their cells' centres.
    index : ndarray of int64, shape (d,)
        The leaf's index.
    grid : LeafGrid
    swept : ndarray of bool, shape (H,) or (0,), optional
        The swept voxels (none where ``None`` or empty).
    chord : ndarray of uint16, shape (H,) or (0,), optional
        The summed chord shares (none kept where ``None`` or empty); zero wherever a
        voxel has no count.

    Raises
    ------
    ValueError
        If a voxel without a count has chord shares.
    """
    d = grid.dim
    n_halo = counts.shape[1]
    seen = (counts[0] | counts[1]) > 0
    occupied = np.flatnonzero(counts[0])
    box = grid.side + 2 * grid.halo_voxels
    local = unpack_keys(hit_keys, d) - _box_origin(index, grid)
    flat = local @ (box ** np.arange(d, dtype=np.int64)) if hit_keys.size else occupied[:0]
    listed = not np.array_equal(flat, occupied)
    keys = unpack_keys(hit_keys, d)
    steps = return_steps(hits, keys, grid.resolution, grid.tree_depth)
    exact = not np.array_equal(step_points(steps, keys, grid.resolution, grid.tree_depth), hits)
    swept_bits = _swept_bits(swept, n_halo)
    flags = (_LISTED if listed else 0) | (_EXACT if exact else 0) | (_SWEPT if swept_bits else 0)
    has_chord = chord is not None and chord.size > 0
    if has_chord:
        assert chord is not None
        if chord.shape != (n_halo,) or np.any(chord[~seen]):
            raise ValueError("chord shares must be per halo voxel, and zero where none is seen")
        flags |= _CHORD
    parts = [
        _HEAD.pack(n_halo, hit_keys.size, flags),
        np.packbits(seen, bitorder="little").tobytes(),
        counts[0, seen].astype(np.uint8).tobytes(),
        counts[1, seen].astype(np.uint8).tobytes(),
    ]
    if listed:
        parts.append(flat.astype("<u4").tobytes())
    if exact:
        parts.append(np.asarray(hits, dtype="<f8").tobytes())
    else:
        parts.append(np.ascontiguousarray(steps.T).astype("<u2").tobytes())
    if has_chord:
        assert chord is not None
        parts.append(chord[seen].astype("<u2").tobytes())
    parts.append(swept_bits)
    return b"".join(parts)


def _swept_bits(swept: np.ndarray | None, n_halo: int) -> bytes:
    """The bitmap of the swept voxels, or nothing where none is swept."""
    if swept is None or not swept.size or not swept.any():
        return b""
    if swept.shape != (n_halo,):
        raise ValueError(f"swept voxels have shape {swept.shape}, expected ({n_halo},)")
    return np.packbits(swept, bitorder="little").tobytes()


def decode_lattice(
    blob: bytes, index: IntArray, grid: LeafGrid
) -> tuple[np.ndarray, IntArray, np.ndarray]:
    """Inverse of :func:`encode_lattice`: ``counts``, ``hit_keys`` and ``hits``.

    Raises
    ------
    OctolgpError
        On a truncated or inconsistent record.
    """
    counts, hit_keys, hits, _ = decode_lattice_swept(blob, index, grid)
    return counts, hit_keys, hits


def decode_lattice_swept(
    blob: bytes, index: IntArray, grid: LeafGrid
) -> tuple[np.ndarray, IntArray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_lattice`: ``counts``, ``hit_keys``, ``hits`` and ``swept``.

    ``swept`` is empty (shape (0,)) where the record has none.

    Raises
    ------
    OctolgpError
        On a truncated or inconsistent record.
    """
    return decode_lattice_record(blob, index, grid)[:4]


def decode_lattice_record(
    blob: bytes, index: IntArray, grid: LeafGrid
) -> tuple[np.ndarray, IntArray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_lattice`: ``counts``, ``hit_keys``, ``hits``, ``swept``, ``chord``.

    ``swept`` and ``chord`` are empty (shape (0,)) where the record has none.

    Raises
    ------
    OctolgpError
        On a truncated or inconsistent record.
    """
    d = grid.dim
    if len(blob) < _HEAD.size:
        raise OctolgpError("lattice evidence is truncated")
    n_halo, r, flags = _HEAD.unpack_from(blob)
    box = grid.side + 2 * grid.halo_voxels
    if n_halo not in (0, box**d) or flags & ~(_LISTED | _EXACT | _SWEPT | _CHORD):
        raise OctolgpError("lattice evidence has a bad header")
    at = _HEAD.size
    n_bits = (n_halo + 7) // 8
    if len(blob) < at + n_bits:
        raise OctolgpError("lattice evidence is truncated")
    bits = np.frombuffer(blob, np.uint8, n_bits, at)
    seen = np.unpackbits(bits, count=n_halo, bitorder="little").astype(bool)
    at += n_bits
    m = int(seen.sum())
    listed, exact = bool(flags & _LISTED), bool(flags & _EXACT)
    n_swept = n_bits if flags & _SWEPT else 0
    n_chord = 2 * m if flags & _CHORD else 0
    need = 2 * m + (4 * r if listed else 0) + (8 if exact else 2) * r * d + n_chord + n_swept
    if len(blob) != at + need:
        raise OctolgpError("lattice evidence has the wrong length")
    counts = np.zeros((2, n_halo), dtype=np.uint8)
    counts[0, seen] = np.frombuffer(blob, np.uint8, m, at)
    counts[1, seen] = np.frombuffer(blob, np.uint8, m, at + m)
    at += 2 * m
    if listed:
        flat = np.frombuffer(blob, "<u4", r, at).astype(np.int64)
        at += 4 * r
    else:
        flat = np.flatnonzero(counts[0])
    if flat.size != r or (r and (flat.min() < 0 or flat.max() >= n_halo)):
        raise OctolgpError("lattice evidence lists returns outside its leaf")
    local = np.stack([(flat // box**a) % box for a in range(d)], axis=1).astype(np.int64)
    keys = local + _box_origin(index, grid)
    if exact:
        hits = np.frombuffer(blob, "<f8", r * d, at).reshape(r, d).astype(np.float64)
    else:
        steps = np.frombuffer(blob, "<u2", r * d, at).reshape(d, r).T
        hits = step_points(steps, keys, grid.resolution, grid.tree_depth)
    swept = np.zeros(0, dtype=bool)
    if n_swept:
        bits = np.frombuffer(blob, np.uint8, n_swept, len(blob) - n_swept)
        swept = np.unpackbits(bits, count=n_halo, bitorder="little").astype(bool)
    chord = np.zeros(0, dtype=np.uint16)
    if n_chord:
        chord = np.zeros(n_halo, dtype=np.uint16)
        chord[seen] = np.frombuffer(blob, "<u2", m, len(blob) - n_swept - n_chord)
    return counts, pack_keys(keys), hits, swept, chord


def encode_lattice_many(
    counts: list[np.ndarray],
    hit_keys: list[IntArray],
    hits: list[np.ndarray],
    indices: IntArray,
    grid: LeafGrid,
    swept: list[np.ndarray] | None = None,
    chord: list[np.ndarray] | None = None,
) -> list[bytes]:
    """:func:`encode_lattice` of many leaves at once (the same bytes, leaf by leaf).

    The arrays of every leaf are stacked so that the work per leaf is a few slices; a
    leaf whose counts are not sized to the halo box (none seen yet) is encoded alone.

    Parameters
    ----------
    counts, hit_keys, hits : list of ndarray
        Per leaf, as :func:`encode_lattice` takes them.
    indices : ndarray of int64, shape (L, d)
        The leaves' indices.
    grid : LeafGrid
    swept : list of ndarray, optional
        Per leaf, its swept voxels (none where ``None``).
    chord : list of ndarray, optional
        Per leaf, its summed chord shares (none where ``None``, or for a leaf, empty).

    Raises
    ------
    ValueError
        If a voxel without a count has chord shares.
    """
    d = grid.dim
    box = grid.side + 2 * grid.halo_voxels
    n_halo = box**d
    none = np.zeros(0, dtype=np.uint16)
    sums = [none] * len(counts) if chord is None else chord
    out: list[bytes | None] = [None] * len(counts)
    sweeps = [] if swept is None else [j for j, s in enumerate(swept) if s.size and s.any()]
    if swept is not None and sweeps:  # the few leaves with swept voxels one by one
        rest = sorted(set(range(len(counts))) - set(sweeps))
        pick = [counts[j] for j in rest], [hit_keys[j] for j in rest], [hits[j] for j in rest]
        blobs = encode_lattice_many(*pick, indices[rest], grid, None, [sums[j] for j in rest])
        for j, blob in zip(rest, blobs, strict=True):
            out[j] = blob
        for j in sweeps:
            out[j] = encode_lattice(
                counts[j], hit_keys[j], hits[j], indices[j], grid, swept[j], sums[j]
            )
        return [b for b in out if b is not None]
    whole = [j for j, c in enumerate(counts) if c.shape == (2, n_halo)]
    for j in sorted(set(range(len(counts))) - set(whole)):  # unsized leaves, one by one
        out[j] = encode_lattice(counts[j], hit_keys[j], hits[j], indices[j], grid, None, sums[j])
    if whole:
        stacked = np.concatenate([counts[j] for j in whole]).reshape(len(whole), 2, n_halo)
        r = np.array([hit_keys[j].size for j in whole], dtype=np.int64)
        keys = unpack_keys(np.concatenate([hit_keys[j] for j in whole]), d)
        points = np.concatenate([np.reshape(hits[j], (-1, d)) for j in whole])
        kept = np.array([sums[j].size > 0 for j in whole])
        stacked_sums = None
        if kept.any():  # zeros for a leaf keeping none: its record gets no sums
            stacked_sums = np.zeros((len(whole), n_halo), dtype=np.uint16)
            for row, j in enumerate(whole):  # one iteration per leaf: a row copy
                if kept[row]:
                    stacked_sums[row] = sums[j]
        blobs = _encode_sized(stacked, r, keys, points, indices[whole], grid, stacked_sums, kept)
        for j, blob in zip(whole, blobs, strict=True):
            out[j] = blob
    return [b for b in out if b is not None]


def _encode_sized(
    counts: np.ndarray,
    r: IntArray,
    keys: IntArray,
    points: np.ndarray,
    indices: IntArray,
    grid: LeafGrid,
    chord: np.ndarray | None = None,
    kept: NDArray[np.bool_] | None = None,
) -> list[bytes]:
    """Records of leaves with sized counts (L, 2, H); returns concatenated leaf by leaf.

    ``chord`` (L, H): the leaves' summed chord shares, written for the leaves ``kept``.
    """
    n, n_halo = counts.shape[0], counts.shape[2]
    d = grid.dim
    box = grid.side + 2 * grid.halo_voxels
    leaf = np.repeat(np.arange(n), r)
    seen = (counts[:, 0] | counts[:, 1]) > 0
    m = seen.sum(axis=1)
    bitmaps = np.packbits(seen, axis=1, bitorder="little")
    occ_h = counts[:, 0][seen]  # leaf by leaf, voxels ascending
    occ_f = counts[:, 1][seen]
    local = keys - np.repeat(_box_origin(indices, grid), r, axis=0)
    flat = local @ (box ** np.arange(d, dtype=np.int64)) if keys.size else np.zeros(0, np.int64)
    rows, cols = np.nonzero(counts[:, 0])
    n_occ = np.bincount(rows, minlength=n)
    listed = n_occ != r
    same = ~listed[leaf] if leaf.size else np.zeros(0, dtype=bool)
    # where the counts agree, compare the returns' voxels with the occupied ones in order
    bad = np.zeros(n, dtype=bool)
    if same.any():
        occ_of = np.zeros(leaf.size, dtype=np.int64)
        occ_of[same] = cols[np.isin(rows, np.flatnonzero(~listed))]
        bad[np.unique(leaf[same & (occ_of != flat)])] = True
    listed |= bad
    steps = return_steps(points, keys, grid.resolution, grid.tree_depth)
    moved = np.any(step_points(steps, keys, grid.resolution, grid.tree_depth) != points, axis=1)
    exact = np.bincount(leaf[moved], minlength=n) > 0
    m_at = np.r_[0, np.cumsum(m)].tolist()
    r_at = np.r_[0, np.cumsum(r)].tolist()
    flat_u4 = flat.astype("<u4")
    steps_u2 = steps.astype("<u2")
    points_f8 = points.astype("<f8")
    has_chord = np.zeros(n, dtype=bool) if chord is None or kept is None else kept
    chord_u2 = np.zeros(0, dtype="<u2")
    if chord is not None:
        if np.any(chord[~seen]):
            raise ValueError("chord shares must be per halo voxel, and zero where none is seen")
        chord_u2 = chord[seen].astype("<u2")  # leaf by leaf, voxels ascending
    out = []
    for j in range(n):  # one leaf per iteration: slices of the stacked arrays
        a, b, ra, rb = m_at[j], m_at[j + 1], r_at[j], r_at[j + 1]
        flags = (_LISTED if listed[j] else 0) | (_EXACT if exact[j] else 0)
        flags |= _CHORD if has_chord[j] else 0
        parts = [
            _HEAD.pack(n_halo, rb - ra, flags),
            bitmaps[j].tobytes(),
            occ_h[a:b].tobytes(),
            occ_f[a:b].tobytes(),
        ]
        if listed[j]:
            parts.append(flat_u4[ra:rb].tobytes())
        if exact[j]:
            parts.append(points_f8[ra:rb].tobytes())
        else:
            parts.append(np.ascontiguousarray(steps_u2[ra:rb].T).tobytes())
        if has_chord[j]:
            parts.append(chord_u2[a:b].tobytes())
        out.append(b"".join(parts))
    return out
