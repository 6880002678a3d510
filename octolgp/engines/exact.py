"""The exact leaf engine: the paper's local GP on hits and free segments of each leaf.

A step's beams become hits and free segments (:func:`octolgp.training.make_training_data`);
a hit goes to every leaf whose halo box holds it, a free segment is clipped to the halo
box of every leaf it crosses (:func:`octolgp.mapping.grid.assign_points`,
:func:`~octolgp.mapping.grid.assign_segments`). A leaf keeps the *first* hit per voxel
and the first free piece per voxel of the piece's end (:meth:`ExactEvidence.extended`),
so its training set never exceeds two items per voxel of its halo box, a revisit that
brings no new voxel leaves the leaf as it was, and inserting scans one by one gives bit
for bit the map of inserting them at once. This keeps a changing world's first state:
the exact engine cannot forget (``OnlineConfig.clear_scans`` is 0).

A leaf with at most ``ExactConfig.max_leaf_items`` items is one GP on all of them
(Matérn 3/2 with integral kernels for the segments, :mod:`octolgp.gp.kernels`); a
larger one is split by the paper's iterative k-means under the cluster cap
(:func:`octolgp.partition.partition`) and each voxel is predicted by its nearest
cluster. PLSC turns the latent mean and variance into P(occupied). This is the
reference the lattice engine (:mod:`octolgp.engines.lattice`) is tested against.

**Honest unknown.** With ``MapConfig.fill_voxels`` at least 0, a leaf also keeps a seen
mask over its halo box: the voxels the lattice engine's observations see
(:func:`octolgp.observations.observe`, occupied or free) and, in 2D, those swept between
beams (:func:`octolgp.sweep.swept_keys`), scattered by the shared rule of
:mod:`octolgp.engines.known`. A voxel with no seen voxel within ``fill_voxels`` holds NaN
(unknown), so both engines know the same voxels; elsewhere the values are the GP's,
exactly those of a map without the mask (``fill_voxels`` -1).
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Iterable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines.base import Evidence, LeafFit, Lookup, read_arrays, stage, with_values
from octolgp.engines.kernel_cache import KernelCache, leaf_blocks
from octolgp.engines.known import grow_seen, halo_pairs, near_leaf, seen_near
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import unpack_keys
from octolgp.gp.clusters import cluster_tree, fit_clusters, predict_nearest
from octolgp.gp.plsc import latent_occupancy
from octolgp.gp.quadrature import items_and_targets, quadrature_spacing
from octolgp.gp.regression import fit_predict
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments, group_keys
from octolgp.mapping.store import Leaf
from octolgp.observations import observe
from octolgp.partition import partition
from octolgp.scan import FloatArray, Scan
from octolgp.sweep import swept_keys
from octolgp.training import IntArray, TrainingData, make_training_data

KERNEL_CACHE_BYTES = 64_000_000
"""RAM for the item covariance blocks of recently refitted leaves
(:mod:`octolgp.engines.kernel_cache`); it saves kernel evaluations, never changes a result."""

_SIZES = struct.Struct("<qq")  # hits, free pieces
_NO_MASK = np.zeros(0, dtype=bool)
_NO_MASK.setflags(write=False)


def _new_first(existing: IntArray, keys: IntArray) -> IntArray:
    """Indices of ``keys`` whose value is not in ``existing`` nor earlier in ``keys``."""
    _, first = np.unique(keys, return_index=True)
    first = np.sort(first)
    if existing.size:
        first = first[~np.isin(keys[first], existing)]
    return first.astype(np.int64)


@dataclass(frozen=True, slots=True)
class ExactEvidence:
    """A leaf's hits and clipped free pieces, each tagged with the packed key of its voxel.

    Attributes
    ----------
    hits : ndarray of shape (h, d)
        Hit points in the halo box, metres, world frame, in time order.
    hit_keys : ndarray of shape (h,)
        Packed voxel key of each hit.
    free_start, free_end : ndarray of shape (s, d)
        Free pieces clipped to the halo box, metres, world frame, in time order.
    free_keys : ndarray of shape (s,)
        Packed voxel key of each piece's end.
    seen : ndarray of bool, shape (H,) or (0,)
        Per halo-box voxel (flat, x fastest), whether a scan observed or swept it
        (:mod:`octolgp.engines.known`); only the voxels within ``fill_voxels`` of the
        leaf, the others never make a voxel of it known. Length 0: no mask, every voxel
        counts as seen (a map with ``fill_voxels`` -1, or a leaf recorded before the
        mask, in map files of version 8 and older).
    """

    hits: FloatArray
    hit_keys: IntArray
    free_start: FloatArray
    free_end: FloatArray
    free_keys: IntArray
    seen: NDArray[np.bool_] = dataclasses.field(default_factory=lambda: _NO_MASK)

    @classmethod
    def empty(cls, dim: int) -> ExactEvidence:
        """No items."""
        none = np.zeros(0, dtype=np.int64)
        return cls(np.zeros((0, dim)), none, np.zeros((0, dim)), np.zeros((0, dim)), none)

    @property
    def n_items(self) -> int:
        """Hits plus free pieces."""
        return int(self.hits.shape[0] + self.free_start.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays."""
        arrays = (self.hits, self.hit_keys, self.free_start, self.free_end, self.free_keys)
        return sum(a.nbytes for a in arrays) + self.seen.nbytes

    def extended(
        self,
        hits: FloatArray,
        hit_keys: IntArray,
        free_start: FloatArray,
        free_end: FloatArray,
        free_keys: IntArray,
    ) -> tuple[ExactEvidence, int]:
        """Add the candidates whose voxel holds no item of their class yet.

        Candidates are in time order; the first one per voxel and class is kept.

        Returns
        -------
        evidence : ExactEvidence
            New evidence (``self`` when nothing was added).
        added : int
            Items added (0 means the leaf's GP would not change).
        """
        new_h = _new_first(self.hit_keys, hit_keys)
        new_f = _new_first(self.free_keys, free_keys)
        if not new_h.size and not new_f.size:
            return self, 0
        out = self
        if new_h.size:
            out = dataclasses.replace(
                out,
                hits=np.concatenate([self.hits, hits[new_h]]),
                hit_keys=np.concatenate([self.hit_keys, hit_keys[new_h]]),
            )
        if new_f.size:
            out = dataclasses.replace(
                out,
                free_start=np.concatenate([self.free_start, free_start[new_f]]),
                free_end=np.concatenate([self.free_end, free_end[new_f]]),
                free_keys=np.concatenate([self.free_keys, free_keys[new_f]]),
            )
        return out, int(new_h.size + new_f.size)


def exact_evidence(leaf: Leaf) -> ExactEvidence:
    """The exact engine's evidence of a leaf (raises ``TypeError`` on another engine's)."""
    ev = leaf.evidence
    if not isinstance(ev, ExactEvidence):
        raise TypeError(f"leaf holds {type(ev).__name__}, not the exact engine's evidence")
    return ev


def gather_evidence(
    data: TrainingData,
    grid: LeafGrid,
    config: MapConfig,
    lookup: Lookup,
    seen_keys: IntArray | None = None,
) -> Evidence:
    """Assign training data to leaves and return the leaves that gain items or known voxels.

    Parameters
    ----------
    data : TrainingData
        Hits and free segments of the step, in time order.
    grid : LeafGrid
    config : MapConfig
        Uses ``resolution`` (free pieces stop half a voxel short of the halo box's
        edge), ``exact.free_voxels`` and ``fill_voxels``.
    lookup : callable
        The current leaf of a packed key, or ``None``; only read, once per touched
        leaf in ascending key order.
    seen_keys : ndarray of int64, shape (m, d), optional
        OctoMap keys of the voxels the step saw (:func:`seen_voxels`): each leaf with
        one within ``fill_voxels`` of it adds it to its seen mask (a leaf is made for it
        where none is). ``None``: the map keeps no seen masks (``fill_voxels`` -1).

    Returns
    -------
    Evidence
        ``changed``: the leaves that gain items or whose known voxels grow (refitted);
        ``kept``: those whose seen mask grows without moving a known voxel (stored with
        their values).
    """
    h_idx, h_leaf = assign_points(grid, data.hits)
    _, s_leaf, a, b = assign_segments(grid, data.seg_start, data.seg_end, 0.5 * config.resolution)
    hits = data.hits[h_idx]
    hit_keys = grid.voxel_keys(hits)
    free_keys = grid.voxel_keys(b, config.exact.free_voxels)
    h_order, h_keys, h_bounds = group_keys(grid.pack(h_leaf))
    s_order, s_keys, s_bounds = group_keys(grid.pack(s_leaf))
    touched = np.union1d(h_keys, s_keys)
    pairs = None
    if seen_keys is not None:
        _, seen_leaf, seen_flat, *_ = halo_pairs(seen_keys, grid)
        near = near_leaf(seen_flat, grid, config.fill_voxels)  # the others never count
        seen_leaf, seen_flat = seen_leaf[near], seen_flat[near]
        touched = np.union1d(touched, seen_leaf)
        pairs = (np.searchsorted(touched, seen_leaf), seen_flat)
    keys = touched.tolist()
    current = [lookup(key) for key in keys]  # one call per touched leaf
    masks = _seen_masks(current, pairs, grid, config.fill_voxels) if pairs is not None else None
    index = unpack_keys(touched, grid.dim)
    changed: list[tuple[int, Leaf]] = []
    kept: list[tuple[int, Leaf]] = []
    new_items = 0
    hi = np.searchsorted(h_keys, touched)
    si = np.searchsorted(s_keys, touched)
    none = np.zeros(0, dtype=np.int64)
    for j, key in enumerate(keys):  # one iteration per touched leaf
        hsel = ssel = none
        if hi[j] < h_keys.size and h_keys[hi[j]] == key:
            hsel = h_order[h_bounds[hi[j]] : h_bounds[hi[j] + 1]]
        if si[j] < s_keys.size and s_keys[si[j]] == key:
            ssel = s_order[s_bounds[si[j]] : s_bounds[si[j] + 1]]
        old = current[j]
        if old is None:
            old = Leaf(index[j].copy(), ExactEvidence.empty(grid.dim))
        evidence, added = exact_evidence(old).extended(
            hits[hsel], hit_keys[hsel], a[ssel], b[ssel], free_keys[ssel]
        )
        refit = added > 0
        if masks is not None and (masks.grown[j] or current[j] is None):
            evidence = dataclasses.replace(evidence, seen=masks.after[j].copy())
            refit = refit or bool(masks.known_moved[j]) or current[j] is None
        elif not added:
            continue
        new_items += added
        (changed if refit else kept).append((key, old.evolve(evidence=evidence)))
    return Evidence(changed, keys, new_items, kept)


@dataclass(frozen=True)
class _Masks:
    """The touched leaves' seen masks after a step (:func:`_seen_masks`)."""

    after: NDArray[np.bool_]
    grown: NDArray[np.bool_]
    known_moved: NDArray[np.bool_]


def _seen_masks(
    leaves: list[Leaf | None], pairs: tuple[IntArray, IntArray], grid: LeafGrid, fill: int
) -> _Masks:
    """The seen masks of the touched leaves with a step's seen voxels added.

    Parameters
    ----------
    leaves : list of Leaf or None
        The touched leaves (``None``: new).
    pairs : tuple of ndarray of int64, shape (p,)
        Per (seen voxel, leaf) pair: the leaf (index into ``leaves``) and the voxel's
        flat index in its halo box.
    grid : LeafGrid
    fill : int
        ``MapConfig.fill_voxels`` (at least 0).

    Returns
    -------
    _Masks
        Per leaf (rows in ``leaves``' order): its mask after the step, shape (H,) (a
        leaf without a mask: every voxel), whether it grew, and whether the leaf's known
        voxels moved with it.
    """
    n_halo = (grid.side + 2 * grid.halo_voxels) ** grid.dim
    before = np.zeros((len(leaves), n_halo), dtype=bool)
    for j, leaf in enumerate(leaves):  # one iteration per touched leaf
        if leaf is not None:
            seen = exact_evidence(leaf).seen
            before[j] = seen if seen.size else True
    after, grown = grow_seen(before, *pairs)
    rows = np.flatnonzero(grown)
    known_moved = np.zeros(len(leaves), dtype=bool)
    if rows.size:
        near = seen_near(np.concatenate([before[rows], after[rows]]), grid, fill)
        known_moved[rows] = np.any(near[: rows.size] != near[rows.size :], axis=1)
    return _Masks(after, grown, known_moved)


def seen_voxels(scans: list[Scan], config: MapConfig) -> IntArray:
    """OctoMap keys of the voxels scans see, shape (m, d): observed or swept.

    The voxels of the lattice engine's observations (:func:`octolgp.observations.observe`,
    occupied or free) then the swept ones (:func:`octolgp.sweep.swept_keys`, 2D).
    """
    keys = observe(scans, config).keys
    swept = swept_keys(scans, config)
    if swept.size:
        keys = np.concatenate([keys, unpack_keys(swept, config.dim)])
    return keys


def predict_leaf(
    leaf: Leaf,
    centres: FloatArray,
    config: MapConfig,
    hp: Hyperparameters,
    cache: KernelCache | None = None,
) -> tuple[FloatArray, FloatArray, int]:
    """Fit a leaf's local GP(s) on its evidence and predict at its voxel centres.

    Parameters
    ----------
    leaf : Leaf
        A leaf holding :class:`ExactEvidence`.
    centres : ndarray of shape (V, d)
        The leaf's voxel centres, metres.
    config : MapConfig
    hp : Hyperparameters
    cache : KernelCache, optional
        Item covariance blocks of earlier fits of this leaf, reused for the items it
        already had (one-GP leaves only); the result does not depend on it.

    Returns
    -------
    mean, var : ndarray of shape (V,)
        Latent posterior (variance without the noise).
    repaired : int
        Kernel matrices that needed a jitter (:func:`octolgp.gp.regression.cholesky`).
    """
    ev = exact_evidence(leaf)
    spacing = quadrature_spacing(config, hp.length_scale)
    cap = config.exact.max_leaf_items
    hits, fs, fe = ev.hits, ev.free_start, ev.free_end
    if ev.n_items == 0:
        return np.zeros(centres.shape[0]), np.full(centres.shape[0], hp.signal_variance), 0
    if ev.n_items <= cap or hits.shape[0] == 0:
        if ev.n_items > cap:  # free space only: an even, deterministic thinning
            keep = np.linspace(0, fs.shape[0] - 1, cap).round().astype(np.int64)
            fs, fe = fs[keep], fe[keep]
            cache = None  # the thinned items are not append-only
        items, y = items_and_targets(hits, fs, fe, config, spacing)
        if cache is None:
            mean, var, repaired = fit_predict(items, y, hp, centres)
            return mean, var, int(repaired)
        tc = config.training
        key = (
            hp.length_scale,
            hp.signal_variance,
            spacing,
            float(tc.min_quadrature_nodes),
            float(tc.max_quadrature_nodes),
        )
        packed = int(LeafGrid.from_config(config).pack(leaf.index[None, :])[0])
        K, Ks = leaf_blocks(packed, hits.shape[0], fs.shape[0], items, centres, hp, key, cache)
        mean, var, repaired = fit_predict(items, y, hp, centres, K=K, Ks=Ks)
        return mean, var, int(repaired)
    # the paper's iterative k-means under the cluster cap, nearest-centre prediction
    data = TrainingData(hits, fs, fe, np.full(fs.shape[0], -1, dtype=np.int64))
    # a lattice at the map resolution is fine enough for a leaf's Voronoi cells
    cells = int(np.ceil(float(np.ptp(centres, axis=0).max()) / config.resolution)) + 3
    clusters = partition(data, config, cells=cells)
    gps = fit_clusters(data, clusters, config, hp)
    tree = cluster_tree(clusters, config.dim)
    mean, var = predict_nearest(tree, gps, centres, hp.signal_variance)
    return mean, var, sum(gp.repaired for gp in gps)


def fit_leaf(
    leaf: Leaf, config: MapConfig, hp: Hyperparameters, cache: KernelCache | None = None
) -> LeafFit:
    """Fit a leaf on its evidence and return it with fresh voxel values (a pure function).

    The voxel centres follow from ``leaf.index`` and the leaf grid of ``config``; the
    latent mean and variance are predicted there (:func:`predict_leaf`), PLSC gives
    P(occupied), and a confident leaf is pruned (:func:`octolgp.engines.base.with_values`).
    A voxel with no seen voxel within ``fill_voxels`` (:func:`octolgp.engines.known.seen_near`
    of the leaf's seen mask) holds NaN; a leaf with no known voxel is not fitted.
    """
    grid = LeafGrid.from_config(config)
    centres = grid.voxel_centres(leaf.index)
    seen = exact_evidence(leaf).seen
    known = None
    if config.fill_voxels >= 0 and seen.size:
        known = seen_near(seen[None], grid, config.fill_voxels)[0]
    if known is not None and not known.any():  # nothing seen near: every voxel unknown
        unknown = np.full(centres.shape[0], np.nan)
        return LeafFit(with_values(leaf, unknown, unknown, unknown, config.prune), 0)
    mean, var, repaired = predict_leaf(leaf, centres, config, hp, cache)
    prob = latent_occupancy(mean, var, hp)
    if known is not None and not known.all():  # no value where nothing near was seen
        mean, var, prob = (np.where(known, v, np.nan) for v in (mean, var, prob))
    return LeafFit(with_values(leaf, mean, var, prob, config.prune), repaired)


class ExactEngine:
    """The exact engine of a map (:class:`octolgp.engines.base.LeafEngine`).

    Parameters
    ----------
    config : MapConfig
        The map's resolved config.
    """

    name = "exact"

    def __init__(self, config: MapConfig) -> None:
        self.config = config
        self.grid = LeafGrid.from_config(config)
        # evidence is deduplicated per leaf, in time order; a scan-level dedup would
        # make one-by-one and all-at-once insertion differ
        self._raw = dataclasses.replace(
            config, training=dataclasses.replace(config.training, dedup=False)
        )
        self.kernel_cache = KernelCache(KERNEL_CACHE_BYTES)

    def evidence(
        self, scans: list[Scan], lookup: Lookup, stats: dict[str, float], *, fresh: bool = True
    ) -> Evidence:
        """Scans → hits, free segments and seen voxels → the leaves that gain items.

        The seen voxels (:func:`seen_voxels`) only where the map keeps seen masks
        (``fill_voxels`` at least 0). A leaf is one GP, so no part of it is ever fresh:
        ``fresh`` is unused.
        """
        with stage(stats, "training"):
            data = make_training_data(scans, self._raw)
            seen = seen_voxels(scans, self.config) if self.config.fill_voxels >= 0 else None
        with stage(stats, "assign"):
            return gather_evidence(data, self.grid, self.config, lookup, seen)

    def fit(
        self,
        leaves: list[Leaf],
        hp: Hyperparameters,
        pool: Executor | None = None,
        *,
        reuse: bool = True,
        fresh: NDArray[np.bool_] | None = None,
    ) -> list[LeafFit]:
        """Fit each leaf on its own (:func:`fit_leaf`), on ``pool``'s threads when given.

        A leaf is one GP here: ``fresh`` (never given by this engine's evidence) is unused.
        """
        cache = self.kernel_cache if reuse else None
        if pool is None or len(leaves) < 2:
            return [fit_leaf(leaf, self.config, hp, cache) for leaf in leaves]
        return list(pool.map(lambda leaf: fit_leaf(leaf, self.config, hp, cache), leaves))

    def rebuilt(self, keys: Iterable[int]) -> None:
        """Drop the cached kernel blocks of leaves whose items were rebuilt."""
        self.kernel_cache.discard(list(keys))

    def empty(self, dim: int) -> ExactEvidence:
        """No items."""
        return ExactEvidence.empty(dim)

    values_from_evidence = False

    def record(self, evidence: object, index: IntArray) -> bytes:
        """The evidence as the map file keeps it: :meth:`encode` (the leaf's values too)."""
        return self.encode(evidence)

    def records(self, evidence: Sequence[object], indices: IntArray) -> list[bytes]:
        """:meth:`record` of many leaves."""
        return [self.encode(ev) for ev in evidence]

    def from_record(self, blob: bytes, index: IntArray) -> ExactEvidence:
        """Inverse of :meth:`record`."""
        return self.decode(blob, int(np.asarray(index).size))

    def encode(self, evidence: object) -> bytes:
        """Item counts, then hits, hit keys, piece starts, ends and keys (little-endian).

        A leaf with a seen mask ends the bytes with it (``np.packbits``, little bit
        order, one bit per halo-box voxel); a leaf without one has the bytes of map files
        of version 8.
        """
        if not isinstance(evidence, ExactEvidence):
            raise TypeError(f"expected ExactEvidence, got {type(evidence).__name__}")
        ev = evidence
        head = _SIZES.pack(ev.hits.shape[0], ev.free_start.shape[0])
        parts = (
            ev.hits.astype("<f8"),
            ev.hit_keys.astype("<i8"),
            ev.free_start.astype("<f8"),
            ev.free_end.astype("<f8"),
            ev.free_keys.astype("<i8"),
        )
        mask = np.packbits(ev.seen, bitorder="little").tobytes() if ev.seen.size else b""
        return head + b"".join(p.tobytes() for p in parts) + mask

    def decode(self, blob: bytes, dim: int) -> ExactEvidence:
        """Inverse of :meth:`encode`."""
        if len(blob) < _SIZES.size:
            raise OctolgpError("exact evidence is truncated")
        h, s = _SIZES.unpack_from(blob)
        if min(h, s) < 0:
            raise OctolgpError("exact evidence has a bad header")
        specs = [(h * dim, "<f8"), (h, "<i8"), (s * dim, "<f8"), (s * dim, "<f8"), (s, "<i8")]
        n_halo = (self.grid.side + 2 * self.grid.halo_voxels) ** dim
        n_bits = (n_halo + 7) // 8
        seen = _NO_MASK
        if len(blob) == _SIZES.size + 8 * (h * (dim + 1) + s * (2 * dim + 1)) + n_bits:
            bits = np.frombuffer(blob, np.uint8, n_bits, len(blob) - n_bits)
            seen = np.unpackbits(bits, count=n_halo, bitorder="little").astype(bool)
            blob = blob[: len(blob) - n_bits]
        hits, hit_keys, fs, fe, free_keys = read_arrays(blob, _SIZES.size, specs)
        return ExactEvidence(
            hits.reshape(h, dim),
            hit_keys,
            fs.reshape(s, dim),
            fe.reshape(s, dim),
            free_keys,
            seen,
        )
