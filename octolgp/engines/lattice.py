"""The lattice leaf engine (the default): voxel observation counts, a shared inducing lattice.

Each scan becomes voxel observations (:func:`octolgp.observations.observe`): per voxel,
whether the scan saw it occupied (a return in it) and whether it saw it free (a free
segment through it). A leaf keeps, per voxel of its halo box and class, a saturating
count of the scans that saw it so (at most ``LatticeConfig.evidence_cap``; free looks up
to ``OnlineConfig.clear_scans`` with forgetting on), updated by the newer-evidence rule
(:func:`octolgp.observations.newer_evidence_wins`), and one measured return per voxel it
sees occupied. The leaf's GP sees the returns at their positions and the free voxels at
their centres, a free look weighing ``LatticeConfig.free_weight`` of a return
(:func:`octolgp.observations.effective_counts`), or, with ``LatticeConfig.free_evidence =
"chord"``, a free voxel weighing ``chord_weight`` times its summed shares of the free
segments' chords through the 16-voxel box holding it, which the leaf keeps per halo voxel beside
the counts (:func:`octolgp.observations.advance_chord`); it is a sparse GP on an inducing lattice
whose kernel tables every leaf shares (:mod:`octolgp.gp.lattice`), so many leaves fit in a
few matrix products. A leaf's counts are a function of the scans in time order, not of
how they were grouped into steps, so inserting scans one by one gives the map of
inserting them at once.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import struct
from collections.abc import Iterable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import gather_kernel
from octolgp.engines.base import (
    Evidence,
    LeafFit,
    Lookup,
    fitted_leaves,
    read_arrays,
    stage,
)
from octolgp.engines.known import grow_seen, halo_pairs, seen_near
from octolgp.engines.lattice_record import (
    decode_lattice_record,
    encode_lattice,
    encode_lattice_many,
)
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import KEY_BITS, pack_keys, unpack_keys
from octolgp.gp.lattice import (
    LatticeGeometry,
    LatticeTables,
    Returns,
    inducing_per_axis,
    lattice_posterior,
    lattice_tables,
)
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.observations import (
    VoxelObservations,
    VoxelState,
    advance,
    advance_chord,
    effective_counts,
    free_inputs,
    observe,
    sorted_contains,
)
from octolgp.scan import FloatArray, Scan
from octolgp.sweep import swept_keys
from octolgp.training import IntArray

_SIZES = struct.Struct("<qq")  # halo voxels of the counts, kept returns
_NONE_SWEPT = np.zeros(0, dtype=bool)
_NONE_SWEPT.setflags(write=False)
_NONE_CHORD = np.zeros(0, dtype=np.uint16)
_NONE_CHORD.setflags(write=False)
_U8, _U16 = np.dtype(np.uint8), np.dtype(np.uint16)


@dataclass(frozen=True, slots=True)
class LatticeEvidence:
    """A leaf's observation counts per halo-box voxel and its kept returns.

    Attributes
    ----------
    counts : ndarray of uint8, shape (2, H)
        Per halo-box voxel (flat, x fastest): scans that saw it occupied (row 0) and
        free (row 1), saturated.
    hit_keys : ndarray of int64, shape (r,)
        Packed voxel keys of the voxels holding a return, ascending.
    hits : ndarray of shape (r, d)
        The return kept for each of them, metres, world frame.
    swept : ndarray of bool, shape (H,) or (0,)
        Per halo-box voxel, whether a scan swept it between two beams
        (:func:`octolgp.sweep.swept_keys`): known for ``LatticeConfig.fill_voxels``, no
        evidence for the GP. Length 0: none swept.
    chord : ndarray of uint16, shape (H,) or (0,)
        Per halo-box voxel, its free looks' summed chord shares since its last return
        (:func:`octolgp.observations.advance_chord`), in ``ray_kernel.CHORD_UNITS``,
        saturated (``LatticeConfig.free_evidence = "chord"``). Length 0: none kept.
    """

    counts: NDArray[np.uint8]
    hit_keys: IntArray
    hits: FloatArray
    swept: NDArray[np.bool_] = dataclasses.field(default_factory=lambda: _NONE_SWEPT)
    chord: NDArray[np.uint16] = dataclasses.field(default_factory=lambda: _NONE_CHORD)

    @classmethod
    def empty(cls, dim: int) -> LatticeEvidence:
        """Nothing seen (counts of zero length: sized on the first observation)."""
        return cls(np.zeros((2, 0), np.uint8), np.zeros(0, np.int64), np.zeros((0, dim)))

    @property
    def n_items(self) -> int:
        """Observed (voxel, class) pairs."""
        return int(np.count_nonzero(self.counts))

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays."""
        arrays = self.counts.nbytes + self.hit_keys.nbytes + self.hits.nbytes
        return arrays + self.swept.nbytes + self.chord.nbytes


def lattice_evidence(leaf: Leaf) -> LatticeEvidence:
    """The lattice engine's evidence of a leaf (raises ``TypeError`` on another engine's)."""
    return lattice_evidence_of(leaf.evidence)


def lattice_evidence_of(evidence: object) -> LatticeEvidence:
    """``evidence`` as the lattice engine's (raises ``TypeError`` on another engine's)."""
    if not isinstance(evidence, LatticeEvidence):
        name = type(evidence).__name__
        raise TypeError(f"leaf holds {name}, not the lattice engine's evidence")
    return evidence


def evidence_of(leaves: list[Leaf]) -> list[LatticeEvidence]:
    """:func:`lattice_evidence` of many leaves (raises ``TypeError`` on another engine's)."""
    evidence = [leaf.evidence for leaf in leaves]
    if set(map(type, evidence)) <= {LatticeEvidence}:
        return cast(list[LatticeEvidence], evidence)
    return [lattice_evidence(leaf) for leaf in leaves]


def _stack(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.stack(arrays)``, faster for many small arrays of one shape."""
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or not next(iter(shapes)):  # none, mixed (np.stack raises) or 0-d
        return np.stack(arrays)
    return np.concatenate(arrays).reshape(len(arrays), *next(iter(shapes)))


def halo_copies(obs: VoxelObservations, grid: LeafGrid) -> tuple[IntArray, IntArray, IntArray]:
    """Every (observed voxel, leaf whose halo box holds it) pair.

    Returns the voxel (index into ``obs``), the leaf's packed key and the voxel's flat
    index in that leaf's halo box, per pair; pairs are grouped by the neighbour offset.
    """
    return halo_pairs(obs.keys, grid)[:3]


def _touched_leaves(
    leaf_key: IntArray, cell: IntArray, origin: tuple[int, ...], extent: tuple[int, ...]
) -> tuple[IntArray, IntArray]:
    """The distinct leaves of the pairs, ascending, and each pair's leaf among them.

    Parameters
    ----------
    leaf_key, cell : ndarray of int64, shape (p,)
        Each pair's leaf: its packed key and its cell
        (:func:`octolgp.engines.known.halo_pairs`).
    origin, extent : tuple of int, length d
        The box of the cells.

    Returns
    -------
    touched : ndarray of int64, shape (t,)
        Packed keys, ascending (``np.unique(leaf_key)``).
    inverse : ndarray of int64, shape (p,)
        Each pair's leaf as an index into ``touched``.
    """
    volume = int(np.prod(extent))
    if volume > 4 * leaf_key.size + 4096:  # a sparse box: hashing beats a table of it
        touched = np.unique(leaf_key)
        return touched, np.searchsorted(touched, leaf_key)
    seen = np.zeros(volume, dtype=bool)
    seen[cell] = True
    cells = np.flatnonzero(seen)
    rank = np.empty(volume, dtype=np.int64)
    rank[cells] = np.arange(cells.size)
    touched = np.zeros(cells.size, dtype=np.int64)
    for a, (o, e) in enumerate(zip(origin, extent, strict=True)):  # per axis
        touched |= (cells % e + o) << (KEY_BITS * a)
        cells = cells // e
    return touched, rank[cell]


def _moved_returns(
    leaves: list[Leaf | None],
    owner: IntArray,
    voxel: IntArray,
    drop: NDArray[np.bool_],
    replace: NDArray[np.bool_],
    position: FloatArray,
    voxel_keys: IntArray,
    dim: int,
) -> dict[int, tuple[IntArray, FloatArray]]:
    """The kept returns of the leaves where some are new or forgotten, in voxel-key order.

    Parameters
    ----------
    leaves : list of Leaf or None
        The touched leaves (``None``: new).
    owner, voxel : ndarray of int64, shape (p,)
        Per (voxel, leaf) pair whose return moves: the leaf (index into ``leaves``) and
        the voxel (row of ``voxel_keys``).
    drop, replace : ndarray of bool, shape (p,)
        The pair's kept return is forgotten; it becomes ``position``.
    position : ndarray of shape (p, d)
    voxel_keys : ndarray of int64, shape (n, d)
        The step's observed voxels' keys, ascending as packed keys (only those of the
        pairs are packed).
    dim : int

    Returns
    -------
    dict
        Per such leaf (index into ``leaves``): its kept returns' packed keys (ascending)
        and positions, arrays of its own.
    """
    if not owner.size:
        return {}
    js = np.flatnonzero(np.bincount(owner, minlength=len(leaves)))
    key_parts, pos_parts = [np.zeros(0, np.int64)], [np.zeros((0, dim))]
    old_n = np.zeros(js.size, dtype=np.int64)
    for row, j in enumerate(js.tolist()):  # one iteration per such leaf
        leaf = leaves[j]
        if leaf is not None:
            ev = lattice_evidence(leaf)
            if ev.hit_keys.size:
                old_n[row] = ev.hit_keys.size
                key_parts.append(ev.hit_keys)
                pos_parts.append(ev.hits)
    old_keys, old_pos = np.concatenate(key_parts), np.concatenate(pos_parts)
    old_owner = np.repeat(js, old_n)
    # a (leaf, voxel) code per old return and per forgotten one: the voxel by its rank
    # among the forgotten ones' voxels (ascending, as their packed keys)
    gone_voxels = np.unique(voxel[drop])
    gone_keys = pack_keys(voxel_keys[gone_voxels])
    n = max(gone_voxels.size, 1)
    rank = np.minimum(np.searchsorted(gone_keys, old_keys), n - 1)
    seen = gone_keys[rank] == old_keys if gone_voxels.size else np.zeros(old_keys.size, bool)
    old_code = np.where(seen, old_owner * n + rank, -1)
    dropped = np.sort(owner[drop] * n + np.searchsorted(gone_voxels, voxel[drop]))
    gone = sorted_contains(dropped, old_code)
    add = np.flatnonzero(replace)
    keys = np.concatenate([old_keys[~gone], pack_keys(voxel_keys[voxel[add]])])
    pos = np.concatenate([old_pos[~gone], position[add]])
    who = np.concatenate([old_owner[~gone], owner[add]])
    order = np.lexsort((keys, who))  # by leaf, then voxel key
    keys, pos, who = keys[order], pos[order], who[order]
    bounds = np.searchsorted(who, np.append(js, js[-1] + 1))
    return {
        j: (keys[lo:hi].copy(), pos[lo:hi].copy())
        for j, lo, hi in zip(js.tolist(), bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)
    }


def advance_copies(
    hits: IntArray, frees: IntArray, obs: VoxelObservations, voxel: IntArray, cap: int
) -> VoxelState:
    """:func:`octolgp.observations.advance` of every (voxel, leaf) copy, once per voxel.

    Every copy of a voxel holds the same state (each observation reaches all its
    copies), so the rule runs once per observed voxel and its result is shared; should
    the copies of a voxel ever differ, it runs on every copy instead.
    """
    unit, at, h, f = _voxel_units(hits, frees, voxel, obs.n_voxels)
    one = advance(h, f, obs, at, cap)
    if unit is None:
        return one
    return VoxelState(
        one.hits[unit], one.frees[unit], one.position[unit], one.replace[unit], one.drop[unit]
    )


def _voxel_units(
    hits: IntArray, frees: IntArray, voxel: IntArray, n: int
) -> tuple[IntArray | None, IntArray, IntArray, IntArray]:
    """The copies' states once per voxel, when every copy of a voxel agrees.

    Parameters
    ----------
    hits, frees : ndarray of int, shape (p,)
        The counts of each (voxel, leaf) copy.
    voxel : ndarray of int64, shape (p,)
        Each copy's voxel, in ``[0, n)``.
    n : int
        Observed voxels.

    Returns
    -------
    unit : ndarray of int64, shape (p,), or None
        Each copy's unit: its voxel when the copies agree (units are voxels), ``None``
        when they differ (each copy is a unit of its own).
    at : ndarray of int64
        Each unit's voxel.
    hits, frees : ndarray of int
        Each unit's counts (for a voxel without copies, any).
    """
    rep = np.zeros(n, dtype=np.int64)
    rep[voxel] = np.arange(voxel.size)  # one copy of each voxel (none: unused)
    h, f = hits[rep], frees[rep]
    if not (np.array_equal(h[voxel], hits) and np.array_equal(f[voxel], frees)):
        return None, voxel, hits, frees
    return voxel, np.arange(n), h, f


def _stored_rows(leaves: list[Leaf | None], n_halo: int, chord: bool) -> NDArray[np.uint8]:
    """The stored counts of leaves, and with ``chord`` their summed chord shares, as rows.

    Zero for a new leaf, counts not yet sized, or sums not kept. A row holds the
    counts' bytes (``2 * n_halo``: :attr:`LatticeEvidence.counts` flat) and, with
    ``chord``, then the sums' (``n_halo`` uint16, native order: the row's second half
    viewed as uint16 is :attr:`LatticeEvidence.chord`). A leaf whose counts and sums are
    the two halves of one buffer (:func:`_own_rows` gives them so) gives that buffer
    as its row; the rows are joined in one copy.

    Returns
    -------
    ndarray of uint8, shape (len(leaves), 2 * n_halo) or (len(leaves), 4 * n_halo)
    """
    width = (4 if chord else 2) * n_halo
    if not leaves:
        return np.zeros((0, width), dtype=np.uint8)
    evidence = iter(evidence_of([leaf for leaf in leaves if leaf is not None]))
    if chord:
        zero = np.zeros(width, dtype=np.uint8)
        rows = [zero if leaf is None else _chord_row(next(evidence), zero) for leaf in leaves]
    else:  # the counts as they are, (2, n_halo) each
        zero = np.zeros((2, n_halo), dtype=np.uint8)
        rows = [
            zero if leaf is None or (c := next(evidence).counts).shape[1] != n_halo else c
            for leaf in leaves
        ]
    return np.concatenate(rows).reshape(len(leaves), width)


def _chord_row(
    ev: LatticeEvidence, zero: NDArray[np.uint8], own: bool = False
) -> NDArray[np.uint8]:
    """A leaf's row of counts and sums (``zero``: a zero row, its width): one buffer or built.

    ``own``: a copy of the leaf's one buffer, never the buffer itself.
    """
    c, w = ev.counts, ev.chord
    whole = _one_buffer(ev, zero.size)
    if whole is not None:
        return whole.copy() if own else whole
    n_halo = zero.size // 4
    row = zero.copy()
    if c.shape[1] == n_halo:
        row[: 2 * n_halo] = c.reshape(-1)
    if w.size == n_halo:
        row[2 * n_halo :] = w.view(np.uint8)
    return row


def _one_buffer(ev: LatticeEvidence, width: int) -> NDArray[np.uint8] | None:
    """The buffer of ``width`` bytes whose halves are the leaf's counts and sums, if one is."""
    whole = ev.chord.base
    if isinstance(whole, np.ndarray) and ev.counts.base is whole and whole.nbytes == width:
        return whole
    return None


def _leaf_sources(
    leaves: list[Leaf | None], n_halo: int, chord: bool
) -> tuple[IntArray, IntArray] | None:
    """The addresses of the leaves' counts and sums, for the compiled gather to read.

    0 where a leaf has none (new, counts not yet sized, sums not kept). ``None`` where a
    leaf's arrays are not C-contiguous uint8 / uint16 (the numpy gather then serves).
    """
    from octolgp.engines import leaf_buffers  # imports numba

    counts: list[np.ndarray | None] = []
    sums: list[np.ndarray | None] = []
    in_buffer: list[int] = []  # leaves whose sums follow their counts in one buffer
    width = 4 * n_halo
    for j, leaf in enumerate(leaves):  # one iteration per leaf
        if leaf is None:
            counts.append(None)
            sums.append(None)
            continue
        ev = leaf.evidence
        if type(ev) is not LatticeEvidence:
            ev = lattice_evidence_of(ev)
        c, w = ev.counts, ev.chord
        if c.shape[1] == n_halo:
            if not (c.dtype is _U8 or c.dtype == _U8) or not c.flags.c_contiguous:
                return None
            counts.append(c)
            if chord and _one_buffer(ev, width) is not None:
                in_buffer.append(j)  # as _new_buffers leaves them: at 2 n_halo bytes on
                sums.append(None)
                continue
        else:
            counts.append(None)
        if chord and w.size == n_halo:
            if not (w.dtype is _U16 or w.dtype == _U16) or not w.flags.c_contiguous:
                return None
            sums.append(w)
        else:
            sums.append(None)
    counts_at = leaf_buffers.addresses(counts)
    chord_at = leaf_buffers.addresses(sums)
    chord_at[in_buffer] = counts_at[in_buffer] + 2 * n_halo
    return counts_at, chord_at


def _new_buffers(
    leaves: list[Leaf | None], new_counts: NDArray[np.bool_], n_halo: int, chord: bool
) -> tuple[list[tuple[NDArray[np.uint8], NDArray[np.uint16] | None]], tuple[IntArray, IntArray]]:
    """Fresh buffers for the leaves with new counts: their stored ones copied, or zero.

    Returns
    -------
    own : list of (counts, sums)
        Per leaf with new counts (ascending): its counts, shape ``(2, n_halo)``, and
        with ``chord`` its sums, the two halves of one buffer of its own (sums ``None``
        without ``chord``), as :func:`_own_rows` gives them.
    targets : tuple of ndarray of int64, shape (len(leaves),) each
        Each leaf's new counts' and sums' addresses (0: a leaf left as it is), for
        :func:`octolgp.engines.leaf_buffers.write_pairs`.
    """
    from octolgp.engines import leaf_buffers  # imports numba

    width = (4 if chord else 2) * n_halo
    sel = np.flatnonzero(new_counts).tolist()
    buffers: list[NDArray[np.uint8]] = []
    if chord:
        zero = np.zeros(width, dtype=np.uint8)
        for j in sel:  # one buffer per leaf with new counts
            leaf = leaves[j]
            buffers.append(
                zero.copy() if leaf is None else _chord_row(lattice_evidence(leaf), zero, own=True)
            )
    else:
        for j in sel:
            leaf = leaves[j]
            c = None if leaf is None else lattice_evidence(leaf).counts
            buffers.append(
                c.copy()
                if c is not None and c.shape[1] == n_halo
                else np.zeros((2, n_halo), np.uint8)
            )
    at = leaf_buffers.addresses(buffers)
    counts_at = np.zeros(len(leaves), dtype=np.int64)
    chord_at = np.zeros(len(leaves), dtype=np.int64)
    counts_at[sel] = at
    if chord:
        chord_at[sel] = at + 2 * n_halo
    own = [_own_view(b, n_halo) for b in buffers]
    return own, (counts_at, chord_at)


def _own_view(
    own: NDArray[np.uint8], n_halo: int
) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
    """A leaf's counts, and sums where ``own`` holds them, as views of its own buffer."""
    if own.ndim == 2:
        return own, None
    return own[: 2 * n_halo].reshape(2, n_halo), own[2 * n_halo :].view(np.uint16)


def _own_rows(
    row: NDArray[np.uint8], n_halo: int
) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
    """A leaf's own counts, and sums where ``row`` holds them, from a row of :func:`_stored_rows`.

    One copy: a row of counts only, shaped ``(2, n_halo)``, is the counts' own array;
    with sums, the counts and sums are views of the two halves of the leaf's one buffer.
    """
    return _own_view(row.copy(), n_halo)


def _advance_chord_pairs(
    voxel: IntArray,
    at_w: IntArray,
    inverse: IntArray,
    flat_chord: NDArray[np.uint16],
    obs: VoxelObservations,
    unit: IntArray | None,
    counts0: tuple[NDArray[np.integer], NDArray[np.integer]],
    free01: tuple[NDArray[np.integer], NDArray[np.integer]],
    refit: NDArray[np.bool_],
    new_counts: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Advance the pairs' summed chord shares: once per voxel where copies agree.

    The numpy form of :func:`octolgp.engines.gather_kernel.chord_rule` and
    :func:`~octolgp.engines.gather_kernel.leaf_flags`, which also
    serves where copies differ. ``unit`` is the counts' (``None``: each copy a unit of
    its own), ``counts0`` the units' stored return and free counts before the step and
    ``free01`` their effective free counts before and after it; writes the new sums
    into ``flat_chord`` and sets ``refit`` / ``new_counts`` for the leaves whose GP
    input / stored sum moved.

    Returns
    -------
    ndarray of bool, shape (p,)
        The pairs whose GP input moved.
    """
    (h0, f0), (ef0, ef1) = counts0, free01
    w_pairs = flat_chord[at_w].astype(np.int64)
    w_unit, w_at, w0, h_w, f_w = None, voxel, w_pairs, h0, f0
    if unit is not None:  # per voxel where the counts' copies agree and the sums' too
        w_unit, w_at, w0, _ = _voxel_units(w_pairs, w_pairs, voxel, obs.n_voxels)
        if w_unit is None:
            h_w, f_w = h0[unit], f0[unit]
    w1 = advance_chord(w0, h_w, f_w, obs, w_at)
    if w_unit is None:  # per copy: the counts' units to copies
        free0, free1 = (ef0, ef1) if unit is None else (ef0[unit], ef1[unit])
    else:
        free0, free1 = ef0, ef1
    w_input: NDArray[np.bool_] = np.where(free1 > 0, w1, 0) != np.where(free0 > 0, w0, 0)
    w_stored = w_input | (w1 != w0)
    if w_unit is not None:
        w1, w_input, w_stored = w1[w_unit], w_input[w_unit], w_stored[w_unit]
    flat_chord[at_w] = w1
    refit[inverse[w_input]] = True
    new_counts[inverse[w_stored]] = True
    return w_input


def gather_observations(
    obs: VoxelObservations,
    grid: LeafGrid,
    config: MapConfig,
    lookup: Lookup,
    *,
    fresh: bool = True,
    swept: IntArray | None = None,
) -> Evidence:
    """Apply a step's voxel observations to the leaves whose halo boxes hold the voxels.

    A leaf is *changed* (refitted) when what its GP sees moved (its effective counts or
    its kept returns), *kept* (stored, not refitted) when only its stored counts moved.
    The rule runs once per observed voxel (every copy of a voxel holds the same state;
    should copies differ, once per copy), and each leaf with new counts gets arrays of
    its own.

    Parameters
    ----------
    obs : VoxelObservations
        The step's observations.
    grid : LeafGrid
    config : MapConfig
        Uses ``lattice.evidence_cap`` and the resolved ``clear_scans``.
    lookup : callable
        The current leaf of a packed key, or ``None``; only read, once per touched
        leaf in ascending key order.
    fresh : bool
        Whether to work out the tiles of each changed leaf that a refit may keep
        (``Evidence.fresh``); a map that fits later refits its leaves whole.
    swept : ndarray of int64, shape (m,), optional
        Packed keys of the voxels the step's scans swept (:func:`octolgp.sweep.swept_keys`):
        each leaf whose halo box holds one keeps it as swept (a leaf is made for it
        where none is), and a leaf with a newly swept voxel is refitted.

    Returns
    -------
    Evidence
        ``new_items`` counts the (voxel, class) inputs of leaf GPs that changed.
    """
    n_obs = obs.n_voxels
    voxel_keys = obs.keys
    if swept is not None and swept.size:
        voxel_keys = np.concatenate([obs.keys, unpack_keys(swept, grid.dim)])
    voxel, leaf_key, flat, cell, origin, extent = halo_pairs(voxel_keys, grid)
    touched, inverse = _touched_leaves(leaf_key, cell, origin, extent)
    swept_pairs = None
    if voxel_keys is not obs.keys:  # the swept voxels' pairs apart
        is_swept = voxel >= n_obs
        swept_pairs = (inverse[is_swept], flat[is_swept])
        voxel, flat, inverse = voxel[~is_swept], flat[~is_swept], inverse[~is_swept]
    keys = touched.tolist()
    n_halo = (grid.side + 2 * grid.halo_voxels) ** grid.dim
    current = [lookup(key) for key in keys]  # one call per touched leaf
    with_chord = obs.chord is not None  # the summed chord shares beside the counts
    cap = config.lattice.evidence_cap
    once = None
    if gather_kernel.AVAILABLE:  # compiled: each leaf's cells read where they are
        from octolgp.engines import leaf_buffers  # imports numba

        sources = _leaf_sources(current, n_halo, with_chord)
        if sources is not None:
            once = leaf_buffers.unit_values(voxel, inverse, flat, n_halo, *sources, obs.n_voxels)
    # the rule and what changes, per unit (a voxel, or a copy should copies differ)
    unit: IntArray | None
    stacked = None
    if once is not None:
        unit, at, (h0, f0, w0) = voxel, np.arange(obs.n_voxels), once
    else:  # numpy: the touched leaves' rows stacked
        stacked = _stored_rows(current, n_halo, with_chord)
        at_h = inverse * stacked.shape[1] + flat  # each pair's return count in stacked.ravel()
        flat_counts = stacked.reshape(-1)
        before_h = flat_counts[at_h].astype(np.int64)
        before_f = flat_counts[at_h + n_halo].astype(np.int64)
        unit, at, h0, f0 = _voxel_units(before_h, before_f, voxel, obs.n_voxels)
    state = (gather_kernel.advance if once is not None else advance)(h0, f0, obs, at, cap)
    # what the leaf GP sees: its effective counts, and the kept returns
    eh0, ef0 = effective_counts(h0, f0, cap, obs.clear_scans)
    eh1, ef1 = effective_counts(state.hits, state.frees, cap, obs.clear_scans)
    d_h, d_f = eh1 != eh0, ef1 != ef0
    moves = state.replace | state.drop
    effective = d_h | d_f | moves
    stored = effective | (state.hits != h0) | (state.frees != f0)
    w_input: NDArray[np.bool_] | None = None  # the pairs whose summed shares, as seen, moved
    own: list[tuple[NDArray[np.uint8], NDArray[np.uint16] | None]] | None = None
    if once is not None:  # one pass over the pairs for the flags, one to write
        w1, chord_flag = (None, None)
        if with_chord:
            w1, chord_flag = gather_kernel.chord_rule(obs, w0, (h0, f0), (ef0, ef1))
        refit, new_counts, gained, w_input = gather_kernel.leaf_flags(
            voxel, inverse, (effective, stored, d_h, d_f), chord_flag, touched.size
        )
        own, targets = _new_buffers(current, new_counts, n_halo, with_chord)
        leaf_buffers.write_pairs(
            voxel, inverse, flat, n_halo, *targets, state.hits, state.frees, w1
        )
    else:
        assert stacked is not None
        if unit is None:  # each copy its own unit
            copies = np.ones(h0.size, dtype=np.int64)
            hits_p, frees_p, effective_p, stored_p = state.hits, state.frees, effective, stored
        else:
            copies = np.bincount(unit, minlength=h0.size)
            hits_p, frees_p = state.hits[unit], state.frees[unit]
            effective_p, stored_p = effective[unit], stored[unit]
        flat_counts[at_h] = hits_p  # the counts become the new ones (a fresh array)
        flat_counts[at_h + n_halo] = frees_p
        refit = np.zeros(touched.size, dtype=bool)
        refit[inverse[effective_p]] = True
        new_counts = np.zeros(touched.size, dtype=bool)
        new_counts[inverse[stored_p]] = True
        gained = int(copies[d_h].sum() + copies[d_f].sum())
        if with_chord:  # the summed chord shares: once per voxel where copies agree
            per_row = stacked.shape[1] // 2  # uint16 per row: the counts, then the sums
            at_w = inverse * per_row + n_halo + flat
            w_input = _advance_chord_pairs(
                voxel,
                at_w,
                inverse,
                flat_counts.view(np.uint16),
                obs,
                unit,
                (h0, f0),
                (ef0, ef1),
                refit,
                new_counts,
            )
    stale_leaf = stale_flat = np.zeros(0, dtype=np.int64)
    if fresh:  # the pairs whose GP input moved
        moved_in = effective if unit is None else effective[unit]
        stale_leaf, stale_flat = inverse[moved_in], flat[moved_in]
        if w_input is not None:
            stale_leaf = np.concatenate([stale_leaf, inverse[w_input]])
            stale_flat = np.concatenate([stale_flat, flat[w_input]])
    new_swept: dict[int, NDArray[np.bool_]] = {}
    if swept_pairs is not None:
        new_swept, gained_at = _sweep_leaves(current, swept_pairs, n_halo)
        grown = np.fromiter(new_swept, dtype=np.int64, count=len(new_swept))
        refit[grown] = True  # which voxels are known moved
        new_counts[grown] = True
        stale_leaf = np.concatenate([stale_leaf, gained_at[0]])
        stale_flat = np.concatenate([stale_flat, gained_at[1]])
    mv = np.flatnonzero(moves if unit is None else moves[unit])  # pairs whose return moves
    mv_unit = mv if unit is None else unit[mv]
    returns = _moved_returns(
        current,
        inverse[mv],
        voxel[mv],
        state.drop[mv_unit],
        state.replace[mv_unit],
        state.position[mv_unit],
        obs.keys,
        grid.dim,
    )
    stale = _stale_tiles(stale_leaf, stale_flat, touched.size, grid, config) if fresh else None
    changed: list[tuple[int, Leaf]] = []
    kept: list[tuple[int, Leaf]] = []
    fresh_tiles: list[NDArray[np.bool_]] = []
    full = grid.voxels_per_leaf
    touched_index = unpack_keys(touched, grid.dim)
    sel = np.flatnonzero(new_counts)
    if own is None:  # each leaf with new counts: its row's arrays of its own
        assert stacked is not None
        rows = stacked if with_chord else stacked.reshape(len(current), 2, n_halo)
        own = [_own_rows(rows[j], n_halo) for j in sel.tolist()]
    for j, r, (counts_j, chord_j) in zip(sel.tolist(), refit[sel].tolist(), own, strict=True):
        leaf = current[j]  # one iteration per leaf with new counts
        moved = returns.get(j)
        if leaf is None:
            hit_keys, hits = moved or (np.zeros(0, np.int64), np.zeros((0, grid.dim)))
            swept_j = new_swept.get(j, _NONE_SWEPT)
            chord_j = _NONE_CHORD if chord_j is None else chord_j
            evidence = LatticeEvidence(counts_j, hit_keys, hits, swept_j, chord_j)
            leaf = Leaf(touched_index[j].copy(), evidence)
        else:
            ev = cast(LatticeEvidence, leaf.evidence)  # checked by _stored_rows
            hit_keys, hits = (ev.hit_keys, ev.hits) if moved is None else moved
            swept_j = new_swept.get(j, ev.swept)
            chord_j = ev.chord if chord_j is None else chord_j
            evidence = LatticeEvidence(counts_j, hit_keys, hits, swept_j, chord_j)
            leaf = leaf.with_evidence(evidence)
        if r:
            changed.append((keys[j], leaf))
            if stale is not None:  # tiles keep their values only where the leaf holds all
                fresh_tiles.append(
                    ~stale[j]
                    if leaf.mean.size == full and not leaf.pending
                    else np.zeros_like(stale[j])
                )
        else:
            kept.append((keys[j], leaf))
    tiles_fresh = None if stale is None or not changed else np.stack(fresh_tiles)
    return Evidence(changed, keys, gained, kept, tiles_fresh)


def _sweep_leaves(
    leaves: list[Leaf | None], pairs: tuple[IntArray, IntArray], n_halo: int
) -> tuple[dict[int, NDArray[np.bool_]], tuple[IntArray, IntArray]]:
    """The swept voxels of the leaves where a step sweeps a voxel not swept before.

    Parameters
    ----------
    leaves : list of Leaf or None
        The touched leaves (``None``: new).
    pairs : tuple of ndarray of int64, shape (p,)
        Per (swept voxel, leaf) pair: the leaf (index into ``leaves``) and the voxel's
        flat index in its halo box.
    n_halo : int

    Returns
    -------
    swept : dict
        Per leaf whose swept voxels grow: all of them, shape (n_halo,), an array of its own.
    gained : tuple of ndarray of int64
        The newly swept voxels: their leaves and flat indices.
    """
    owner, flat = pairs
    js = np.unique(owner)
    rank = np.searchsorted(js, owner)
    before = np.zeros((js.size, n_halo), dtype=bool)
    for row, j in enumerate(js.tolist()):  # one iteration per leaf swept
        leaf = leaves[j]
        if leaf is not None:
            old = lattice_evidence(leaf).swept
            if old.size == n_halo:
                before[row] = old
    after, grew = grow_seen(before, rank, flat)
    rows, cols = np.nonzero(after & ~before)
    grown = np.flatnonzero(grew).tolist()
    return {int(js[r]): after[r].copy() for r in grown}, (js[rows], cols)


def _stale_tiles(
    leaf: IntArray, flat: IntArray, n_leaves: int, grid: LeafGrid, config: MapConfig
) -> NDArray[np.bool_] | None:
    """Per leaf, the tiles whose halo boxes hold a voxel whose GP input changed.

    Parameters
    ----------
    leaf, flat : ndarray of int64, shape (p,)
        The changed (voxel, leaf) copies: the leaf and the voxel's flat index in its
        halo box.
    n_leaves : int
    grid : LeafGrid
    config : MapConfig

    Returns
    -------
    ndarray of bool, shape (n_leaves, tiles per leaf), or None
        ``None`` where a leaf is one tile.
    """
    layout = tile_layout(grid, config.tile_voxels)
    n_tiles = layout.window.shape[0]
    if n_tiles == 1:
        return None
    n_halo = (grid.side + 2 * grid.halo_voxels) ** grid.dim
    changed = np.zeros((n_leaves, n_halo), dtype=bool)
    changed[leaf, flat] = True
    out: NDArray[np.bool_] = np.any(changed[:, layout.window], axis=2)
    return out


def lattice_geometry(config: MapConfig, hp: Hyperparameters) -> LatticeGeometry:
    """The lattice of a map's GP tiles: tile and halo in voxels, lattice points per axis.

    A tile is ``LatticeConfig.tile_voxels`` on an edge (the leaf itself where tiles are
    as large), with the leaf grid's halo.
    """
    grid = LeafGrid.from_config(config)
    tile = config.tile_voxels
    k_max = config.max_inducing_per_axis
    box = tile + 2 * grid.halo_voxels
    edge = box * grid.resolution
    k_min = config.min_inducing_per_axis
    k = inducing_per_axis(edge, hp.length_scale, config.inducing_spacing, k_min, k_max)
    return LatticeGeometry(config.dim, tile, grid.halo_voxels, k, grid.resolution)


@dataclass(frozen=True)
class TileLayout:
    """Where the GP tiles of a leaf sit in its halo box and among its voxels.

    Tiles are numbered x fastest, as are the voxels of a tile's halo box and of a tile
    (the orders of :class:`octolgp.gp.lattice.LatticeGeometry`).

    Attributes
    ----------
    per_axis : int
        Tiles per axis, ``T = side / tile``.
    tile, halo : int
        Voxels along a tile's edge, and the halo on every side.
    window : ndarray of int64, shape (T**d, (tile + 2 halo)**d)
        Per tile, its halo box's voxels as flat indices into the leaf's halo box.
    voxels : ndarray of int64, shape (T**d, tile**d)
        Per tile, its voxels as flat indices into the leaf's voxels.
    corner : ndarray of int64, shape (T**d, d)
        Each tile's lower corner relative to the leaf's, in voxels.
    """

    per_axis: int
    tile: int
    halo: int
    window: IntArray
    voxels: IntArray
    corner: IntArray


def _flat_offsets(edge: int, stride: int, dim: int) -> IntArray:
    """Flat indices, in a box of edge ``stride``, of a cube of ``edge`` at its origin (x fastest)."""
    steps = np.arange(edge, dtype=np.int64)
    grids = np.meshgrid(*([steps] * dim), indexing="ij")
    coords = np.stack([g.ravel(order="F") for g in grids], axis=1)
    out: IntArray = coords @ (stride ** np.arange(dim, dtype=np.int64))
    return out


@functools.lru_cache(maxsize=8)
def tile_layout(grid: LeafGrid, tile: int) -> TileLayout:
    """The tiles of ``tile`` voxels of a leaf of ``grid`` (memoised; read-only arrays)."""
    side, halo, d = grid.side, grid.halo_voxels, grid.dim
    per_axis = side // tile
    box = side + 2 * halo
    corner = _flat_offsets(per_axis, per_axis, d)  # tile numbers, then their coordinates
    corner = np.stack([(corner // per_axis**a) % per_axis for a in range(d)], axis=1) * tile
    window = (corner @ (box ** np.arange(d)))[:, None] + _flat_offsets(tile + 2 * halo, box, d)
    voxels = (corner @ (side ** np.arange(d)))[:, None] + _flat_offsets(tile, side, d)
    for a in (window, voxels, corner):
        a.setflags(write=False)
    return TileLayout(per_axis, tile, halo, window, voxels, corner)


def tiles_holding(coords: IntArray, layout: TileLayout) -> tuple[IntArray, IntArray]:
    """Every (voxel, tile) pair where the tile's halo box holds the voxel.

    Parameters
    ----------
    coords : ndarray of int64, shape (n, d)
        Voxels in a leaf's halo box.
    layout : TileLayout

    Returns
    -------
    row, tile : ndarray of int64, shape (p,)
        The voxel (row of ``coords``) and the tile's number of each pair.
    """
    t, h, T = layout.tile, layout.halo, layout.per_axis
    d = coords.shape[1]
    top = [np.minimum(coords[:, a] // t, T - 1) for a in range(d)]  # the highest tile per axis
    reach = -(-(t + 2 * h) // t)  # tiles per axis whose halo box may hold a voxel
    tile_parts, row_parts = [], []
    for offset in itertools.product(range(reach), repeat=d):  # candidate tiles
        o = [top[a] - offset[a] for a in range(d)]
        ok = np.ones(coords.shape[0], dtype=bool)
        for a in range(d):
            ok &= (o[a] >= 0) & (coords[:, a] < o[a] * t + t + 2 * h)
        rows = np.flatnonzero(ok)
        number = np.zeros(rows.size, dtype=np.int64)
        for a in range(d):
            number += o[a][rows] * T**a
        tile_parts.append(number)
        row_parts.append(rows)
    return np.concatenate(row_parts), np.concatenate(tile_parts)


def tile_returns(
    kept: KeptReturns,
    layout: TileLayout,
    tile_lo: FloatArray,
    fitted: NDArray[np.bool_] | None = None,
) -> Returns:
    """Leaves' returns split into their tiles: each return in every tile whose halo box holds it.

    Parameters
    ----------
    kept : KeptReturns
        The leaves' returns.
    layout : TileLayout
    tile_lo : ndarray of shape (L T**d, d)
        Each tile's lower corner (leaf after leaf, tiles in layout order), world frame,
        metres: a tile's returns are relative to it, computed as a leaf of the tile's
        size computes its own.
    fitted : ndarray of bool, shape (L T**d,), optional
        The tiles to keep (default: all); the others are left out.

    Returns
    -------
    tiles : Returns
        Per tile kept, its returns relative to the tile's lower corner, in the leaf's
        order.
    """
    T = layout.per_axis
    points = kept.points
    if T == 1 and fitted is None:  # the leaf is its one tile
        return points
    d = points.points.shape[1]
    n_tiles = points.counts.size * T**d
    n_out = n_tiles if fitted is None else int(fitted.sum())
    if not points.points.shape[0]:
        return Returns(points.points, points.weights, np.zeros(n_out, dtype=np.int64))
    owner = np.repeat(np.arange(points.counts.size), points.counts)
    rows, number = tiles_holding(kept.coords, layout)
    number += owner[rows] * T**d
    if fitted is not None:  # only the tiles fitted, numbered among themselves
        keep = fitted[number]
        rows, number = rows[keep], number[keep]
        rank = np.cumsum(fitted) - 1
        lo, number = tile_lo[number], rank[number]
    else:
        lo = tile_lo[number]
    order = np.lexsort((rows, number))  # by tile, then the leaf's order
    counts = np.bincount(number, minlength=n_out).astype(np.int64)
    return Returns(kept.absolute[rows[order]] - lo[order], points.weights[rows[order]], counts)


@functools.lru_cache(maxsize=8)
def map_tables(config: MapConfig, hp: Hyperparameters) -> LatticeTables:
    """The lattice tables of a map (:func:`octolgp.gp.lattice.lattice_tables`), memoised.

    A pure function of its frozen arguments; the cache only saves recomputing them.
    """
    return lattice_tables(lattice_geometry(config, hp), hp)


def return_points(leaves: list[Leaf], grid: LeafGrid, evidence_cap: int) -> Returns:
    """Each leaf's kept returns relative to its lower corner (metres), with their weights.

    A voxel seen occupied contributes its kept return, weighing ``min(counts[0, v],
    evidence_cap)``.
    """
    evidence = evidence_of(leaves)
    return _return_points(leaves, evidence, None, grid, evidence_cap).points


@dataclass(frozen=True)
class KeptReturns:
    """Leaves' kept returns, flat (leaf after leaf), as the tiles need them.

    Attributes
    ----------
    points : Returns
        Relative to each leaf's lower corner, with weights and counts per leaf.
    coords : ndarray of int64, shape (R, d)
        Each return's voxel in its leaf's halo box.
    absolute : ndarray of shape (R, d)
        The returns, world frame, metres.
    """

    points: Returns
    coords: IntArray
    absolute: FloatArray


def _return_points(
    leaves: list[Leaf],
    evidence: list[LatticeEvidence],
    hit_counts: NDArray[np.uint8] | None,
    grid: LeafGrid,
    evidence_cap: int,
) -> KeptReturns:
    """:func:`return_points` of leaves whose evidence is read already, and their voxels.

    ``hit_counts``: the leaves' return counts, shape (len(leaves), H), or ``None`` to
    read them from ``evidence``.
    """
    box, halo, d = grid.side + 2 * grid.halo_voxels, grid.halo_voxels, grid.dim
    n_kept = np.array([ev.hit_keys.size for ev in evidence], dtype=np.int64)
    if not n_kept.sum():
        none = np.zeros((0, d))
        return KeptReturns(Returns(none, np.zeros(0), n_kept), np.zeros((0, d), np.int64), none)
    index = _stack([leaf.index for leaf in leaves])
    owner = np.repeat(np.arange(len(leaves)), n_kept)
    keys = np.concatenate([ev.hit_keys for ev in evidence])
    coords = unpack_keys(keys, d) - (index[owner] * grid.side - halo)
    flat = coords @ (box ** np.arange(d, dtype=np.int64))
    if hit_counts is None:
        hit_counts = np.stack([ev.counts[0] for ev in evidence])
    weights = np.minimum(hit_counts[owner, flat], evidence_cap).astype(np.float64)
    lo, _ = grid.box(index)
    absolute = np.concatenate([ev.hits for ev in evidence])
    return KeptReturns(Returns(absolute - lo[owner], weights, n_kept), coords, absolute)


def fit_lattice_leaves(
    leaves: list[Leaf],
    config: MapConfig,
    hp: Hyperparameters,
    pool: Executor | None = None,
    fresh: NDArray[np.bool_] | None = None,
) -> list[LeafFit]:
    """Fit leaves on their observation counts, all at once (pure).

    Each tile's latent posterior at its voxel centres comes from
    :func:`octolgp.gp.lattice.lattice_posterior`, then PLSC (stored as float32) and
    pruning, decided on the stored P. With ``pool`` the tiles are split into
    ``config.n_jobs`` runs.

    Parameters
    ----------
    leaves : list of Leaf
    config : MapConfig
    hp : Hyperparameters
    pool : Executor, optional
    fresh : ndarray of bool, shape (len(leaves), tiles per leaf), optional
        Tiles whose stored values are those of the leaf's evidence already (their halo
        boxes saw no change): they keep them and are not refitted. Default: none.

    Returns
    -------
    list of LeafFit
        One per leaf, in order (a lattice fit never needs a jitter repair).
    """
    if not leaves:
        return []
    lc = config.lattice
    tables = map_tables(config, hp)
    evidence = evidence_of(leaves)
    stored = _stack([ev.counts for ev in evidence])
    grid = LeafGrid.from_config(config)
    n_halo = (grid.side + 2 * grid.halo_voxels) ** grid.dim
    if stored.shape[2] != n_halo:
        raise ValueError(f"lattice leaves hold {stored.shape[2]} voxels, expected {n_halo}")
    kept = _return_points(leaves, evidence, stored[:, 0], grid, lc.evidence_cap)
    layout = tile_layout(grid, config.tile_voxels)
    n, n_tiles = len(leaves), layout.window.shape[0]
    todo = None if fresh is None or not fresh.any() else ~fresh.reshape(-1)
    swept = None  # the leaves' swept voxels, where any leaf has some
    if any(ev.swept.size for ev in evidence):
        swept = np.zeros((n, stored.shape[2]), dtype=bool)
        for row, ev in enumerate(evidence):  # one iteration per leaf
            if ev.swept.size:
                swept[row] = ev.swept
    if 0 <= config.fill_voxels <= layout.halo:  # a tile that sees nothing has no value
        seen = tiles_seeing(stored, layout, swept).reshape(-1)
        if not seen.all():
            todo = seen if todo is None else todo & seen
    which = np.arange(n * n_tiles) if todo is None else np.flatnonzero(todo)
    leaf_of, tile_of = which // n_tiles, which % n_tiles  # the tiles to fit
    returns = kept.points
    if n_tiles > 1 or todo is not None:
        tiles = dataclasses.replace(
            grid, leaf_depth=grid.leaf_depth + int(np.log2(layout.per_axis))
        )
        index = _stack([leaf.index for leaf in leaves])
        tile_index = (index * layout.per_axis)[:, None, :] + layout.corner // layout.tile
        tile_lo, _ = tiles.box(tile_index.reshape(-1, grid.dim))
        returns = tile_returns(kept, layout, tile_lo, todo)
    runs = 1 if pool is None else max(1, min(which.size, config.n_jobs))
    bounds = np.linspace(0, which.size, runs + 1).round().astype(int)
    parts = [(lo, hi, returns.leaves(lo, hi)) for lo, hi in itertools.pairwise(bounds)]
    flat_stored = stored.reshape(-1)
    flat_chord = None  # the leaves' summed chord shares, where free evidence is chord
    if config.free_evidence == "chord":
        none = np.zeros(n_halo, dtype=np.uint16)
        flat_chord = _stack([ev.chord if ev.chord.size == n_halo else none for ev in evidence])
        flat_chord = flat_chord.reshape(-1)

    def run(part: tuple[int, int, Returns]) -> tuple[np.ndarray, ...]:
        """Counts → the tiles' latent posteriors and P, as stored (float32), on a pool thread."""
        lo, hi, tile_points = part
        at = leaf_of[lo:hi, None] * (2 * n_halo) + layout.window[tile_of[lo:hi]]
        hits, frees = effective_counts(
            np.take(flat_stored, at),
            np.take(flat_stored, at + n_halo),
            lc.evidence_cap,
            config.clear_scans,
        )
        chord = None
        if flat_chord is not None:
            chord = np.take(
                flat_chord, leaf_of[lo:hi, None] * n_halo + layout.window[tile_of[lo:hi]]
            )
        free_in, weight = free_inputs(frees, chord, config)
        mean, var = lattice_posterior(tables, hits, free_in, weight, tile_points)
        prob = latent_occupancy(mean, var, hp)
        return mean.astype(np.float32), var.astype(np.float32), prob.astype(np.float32)

    if not which.size:  # no tile sees anything: every voxel reads unknown
        width = layout.voxels.shape[1]
        results = [tuple(np.zeros((0, width), np.float32) for _ in range(3))]
    elif pool is None or runs < 2:
        results = [run(p) for p in parts]
    else:
        results = list(pool.map(run, parts))
    tile_values = [np.concatenate([r[i] for r in results]) for i in range(3)]
    if n_tiles == 1 and todo is None:
        mean, var, prob = tile_values
    else:  # the tiles' voxels into their leaves', over the values kept
        mean, var, prob = (np.empty((n, grid.voxels_per_leaf), np.float32) for _ in range(3))
        if fresh is not None and fresh.any():
            partial = np.flatnonzero(fresh.any(axis=1))
            for out, name in ((mean, "mean"), (var, "var"), (prob, "prob")):
                out[partial] = _stack([getattr(leaves[j], name) for j in partial.tolist()])
        voxels = layout.voxels[tile_of]
        for out, values in zip((mean, var, prob), tile_values, strict=True):
            out[leaf_of[:, None], voxels] = values
    if config.fill_voxels >= 0:  # no value where no voxel near was observed or swept
        far = ~observed_near(stored, grid, config.fill_voxels, swept)
        for values in (mean, var, prob):
            values[far] = np.nan
    fitted = fitted_leaves(leaves, mean, var, prob, config.prune)
    return [LeafFit(leaf, 0) for leaf in fitted]


def tiles_seeing(
    stored: NDArray[np.uint8], layout: TileLayout, swept: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """Whether each tile's halo box holds an observed or swept voxel.

    A tile whose halo box holds none has no voxel within ``lattice.fill_voxels`` (at
    most the tile's halo) of an observed or swept one, so every voxel of it reads
    unknown and its fit can be left out.

    Parameters
    ----------
    stored : ndarray of uint8, shape (n, 2, H)
        The leaves' stored counts over their halo boxes (x fastest).
    layout : TileLayout
    swept : ndarray of bool, shape (n, H), optional
        The leaves' swept voxels over their halo boxes (none where ``None``).

    Returns
    -------
    ndarray of bool, shape (n, tiles per leaf)
    """
    seen = (stored[:, 0] | stored[:, 1]) > 0
    if swept is not None:
        seen |= swept
    out: NDArray[np.bool_] = np.any(seen[:, layout.window], axis=2)
    return out


def observed_near(
    stored: NDArray[np.uint8],
    grid: LeafGrid,
    fill: int,
    swept: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Whether each leaf voxel has an observed or swept voxel within ``fill`` voxels.

    Within ``fill`` voxels along every axis: a cube of edge ``2 fill + 1``
    (:func:`octolgp.engines.known.seen_near` of the voxels with counts or swept).

    Parameters
    ----------
    stored : ndarray of uint8, shape (n, 2, H)
        The leaves' stored counts over their halo boxes (x fastest).
    grid : LeafGrid
    fill : int
        At most the leaf's halo in voxels, so that the halo box holds every voxel that
        counts.
    swept : ndarray of bool, shape (n, H), optional
        The leaves' swept voxels over their halo boxes (none where ``None``).

    Returns
    -------
    ndarray of bool, shape (n, V)
        Per leaf, in its voxel order (x fastest).
    """
    known = (stored[:, 0] | stored[:, 1]) > 0
    if swept is not None:
        known |= swept
    return seen_near(known, grid, fill)


class LatticeEngine:
    """The lattice engine of a map (:class:`octolgp.engines.base.LeafEngine`).

    Parameters
    ----------
    config : MapConfig
        The map's resolved config.
    """

    name = "lattice"

    def __init__(self, config: MapConfig) -> None:
        self.config = config
        self.grid = LeafGrid.from_config(config)

    def evidence(
        self, scans: list[Scan], lookup: Lookup, stats: dict[str, float], *, fresh: bool = True
    ) -> Evidence:
        """Scans → voxel observations → the leaves whose counts move."""
        with stage(stats, "training"):
            obs = observe(scans, self.config)
            swept = swept_keys(scans, self.config)
        with stage(stats, "assign"):
            return gather_observations(
                obs, self.grid, self.config, lookup, fresh=fresh, swept=swept
            )

    def fit(
        self,
        leaves: list[Leaf],
        hp: Hyperparameters,
        pool: Executor | None = None,
        *,
        reuse: bool = True,
        fresh: NDArray[np.bool_] | None = None,
    ) -> list[LeafFit]:
        """Fit all the leaves together (:func:`fit_lattice_leaves`), but their fresh tiles."""
        return fit_lattice_leaves(leaves, self.config, hp, pool, fresh)

    def rebuilt(self, keys: Iterable[int]) -> None:
        """Nothing is cached per leaf."""

    def empty(self, dim: int) -> LatticeEvidence:
        """Nothing seen."""
        return LatticeEvidence.empty(dim)

    values_from_evidence = True

    def record(self, evidence: object, index: IntArray) -> bytes:
        """The compact record (:func:`octolgp.engines.lattice_record.encode_lattice`)."""
        ev = lattice_evidence_of(evidence)
        return encode_lattice(ev.counts, ev.hit_keys, ev.hits, index, self.grid, ev.swept, ev.chord)

    def records(self, evidence: Sequence[object], indices: IntArray) -> list[bytes]:
        """:meth:`record` of many leaves at once (the same bytes)."""
        evs = [lattice_evidence_of(ev) for ev in evidence]
        counts = [ev.counts for ev in evs]
        keys, hits = [ev.hit_keys for ev in evs], [ev.hits for ev in evs]
        swept, chord = [ev.swept for ev in evs], [ev.chord for ev in evs]
        return encode_lattice_many(counts, keys, hits, indices, self.grid, swept, chord)

    def from_record(self, blob: bytes, index: IntArray) -> LatticeEvidence:
        """Inverse of :meth:`record`."""
        return LatticeEvidence(*decode_lattice_record(blob, index, self.grid))

    def encode(self, evidence: object) -> bytes:
        """Sizes, counts (uint8), kept returns' keys and positions, chord shares, swept bitmap.

        The chord shares follow the returns where the leaf keeps them; the swept voxels'
        bitmap (``np.packbits``, little bit order) ends the bytes where a voxel is swept.
        """
        ev = lattice_evidence_of(evidence)
        head = _SIZES.pack(ev.counts.shape[1], ev.hit_keys.size)
        parts = [
            np.ascontiguousarray(ev.counts, dtype=np.uint8),
            ev.hit_keys.astype("<i8"),
            ev.hits.astype("<f8"),
        ]
        if ev.chord.size:
            parts.append(ev.chord.astype("<u2"))
        if ev.swept.any():
            parts.append(np.packbits(ev.swept, bitorder="little"))
        return head + b"".join(p.tobytes() for p in parts)

    def decode(self, blob: bytes, dim: int) -> LatticeEvidence:
        """Inverse of :meth:`encode`."""
        if len(blob) < _SIZES.size:
            raise OctolgpError("lattice evidence is truncated")
        n_halo, r = _SIZES.unpack_from(blob)
        if min(n_halo, r) < 0:
            raise OctolgpError("lattice evidence has a bad header")
        specs = [(2 * n_halo, "u1"), (r, "<i8"), (r * dim, "<f8")]
        n_bits = (n_halo + 7) // 8
        base = _SIZES.size + 2 * n_halo + 8 * r * (1 + dim)
        swept, chord = _NONE_SWEPT, _NONE_CHORD
        if n_halo and len(blob) in (base + n_bits, base + 2 * n_halo + n_bits):
            bits = np.frombuffer(blob, np.uint8, n_bits, len(blob) - n_bits)
            swept = np.unpackbits(bits, count=n_halo, bitorder="little").astype(bool)
            blob = blob[: len(blob) - n_bits]
        if n_halo and len(blob) == base + 2 * n_halo:
            chord = np.frombuffer(blob, "<u2", n_halo, base).astype(np.uint16)
            blob = blob[:base]
        counts, hit_keys, hits = read_arrays(blob, _SIZES.size, specs)
        return LatticeEvidence(
            counts.reshape(2, n_halo), hit_keys, hits.reshape(r, dim), swept, chord
        )
