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
from octolgp.errors import OctolgpError
from octolgp.gp.clusters import cluster_tree, fit_clusters, predict_nearest
from octolgp.gp.plsc import latent_occupancy
from octolgp.gp.quadrature import items_and_targets, quadrature_spacing
from octolgp.gp.regression import fit_predict
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments, group_keys
from octolgp.mapping.store import Leaf
from octolgp.partition import partition
from octolgp.scan import FloatArray, Scan
from octolgp.training import IntArray, TrainingData, make_training_data

KERNEL_CACHE_BYTES = 64_000_000
"""RAM for the item covariance blocks of recently refitted leaves
(:mod:`octolgp.engines.kernel_cache`); it saves kernel evaluations, never changes a result."""

_SIZES = struct.Struct("<qq")  # hits, free pieces


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
    """

    hits: FloatArray
    hit_keys: IntArray
    free_start: FloatArray
    free_end: FloatArray
    free_keys: IntArray

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
        return sum(a.nbytes for a in arrays)

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
    data: TrainingData, grid: LeafGrid, config: MapConfig, lookup: Lookup
) -> Evidence:
    """Assign training data to leaves and return the leaves that gain items.

    Parameters
    ----------
    data : TrainingData
        Hits and free segments of the step, in time order.
    grid : LeafGrid
    config : MapConfig
        Uses ``resolution`` (free pieces stop half a voxel short of the halo box's
        edge) and ``exact.free_voxels``.
    lookup : callable
        The current leaf of a packed key, or ``None``; only read.
    """
    h_idx, h_leaf = assign_points(grid, data.hits)
    _, s_leaf, a, b = assign_segments(grid, data.seg_start, data.seg_end, 0.5 * config.resolution)
    hits = data.hits[h_idx]
    hit_keys = grid.voxel_keys(hits)
    free_keys = grid.voxel_keys(b, config.exact.free_voxels)
    h_order, h_keys, h_bounds = group_keys(grid.pack(h_leaf))
    s_order, s_keys, s_bounds = group_keys(grid.pack(s_leaf))
    touched = np.union1d(h_keys, s_keys)
    changed: list[tuple[int, Leaf]] = []
    new_items = 0
    hi = np.searchsorted(h_keys, touched)
    si = np.searchsorted(s_keys, touched)
    none = np.zeros(0, dtype=np.int64)
    for j, key in enumerate(touched.tolist()):  # one iteration per touched leaf
        hsel = ssel = none
        if hi[j] < h_keys.size and h_keys[hi[j]] == key:
            hsel = h_order[h_bounds[hi[j]] : h_bounds[hi[j] + 1]]
        if si[j] < s_keys.size and s_keys[si[j]] == key:
            ssel = s_order[s_bounds[si[j]] : s_bounds[si[j] + 1]]
        old = lookup(key)
        if old is None:
            index = h_leaf[hsel[0]] if hsel.size else s_leaf[ssel[0]]
            old = Leaf(np.asarray(index, dtype=np.int64).copy(), ExactEvidence.empty(grid.dim))
        evidence, added = exact_evidence(old).extended(
            hits[hsel], hit_keys[hsel], a[ssel], b[ssel], free_keys[ssel]
        )
        if added:
            new_items += added
            changed.append((key, old.evolve(evidence=evidence)))
    return Evidence(changed, touched.tolist(), new_items)


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
    """
    centres = LeafGrid.from_config(config).voxel_centres(leaf.index)
    mean, var, repaired = predict_leaf(leaf, centres, config, hp, cache)
    prob = latent_occupancy(mean, var, hp)
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
        """Scans → hits and free segments → the leaves that gain items.

        A leaf is one GP, so no part of it is ever fresh: ``fresh`` is unused.
        """
        with stage(stats, "training"):
            data = make_training_data(scans, self._raw)
        with stage(stats, "assign"):
            return gather_evidence(data, self.grid, self.config, lookup)

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
        """Item counts, then hits, hit keys, piece starts, ends and keys (little-endian)."""
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
        return head + b"".join(p.tobytes() for p in parts)

    def decode(self, blob: bytes, dim: int) -> ExactEvidence:
        """Inverse of :meth:`encode`."""
        if len(blob) < _SIZES.size:
            raise OctolgpError("exact evidence is truncated")
        h, s = _SIZES.unpack_from(blob)
        if min(h, s) < 0:
            raise OctolgpError("exact evidence has a bad header")
        specs = [(h * dim, "<f8"), (h, "<i8"), (s * dim, "<f8"), (s * dim, "<f8"), (s, "<i8")]
        hits, hit_keys, fs, fe, free_keys = read_arrays(blob, _SIZES.size, specs)
        return ExactEvidence(
            hits.reshape(h, dim), hit_keys, fs.reshape(s, dim), fe.reshape(s, dim), free_keys
        )
