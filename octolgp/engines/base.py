"""The seam between the online map and its leaf engines.

A leaf engine turns a step's scans into evidence per leaf and fits leaves on their
evidence, OctoMap's ``computeUpdate`` and the per-leaf GP of Kim & Kim. The map
(:class:`octolgp.mapping.online.OnlineMap`) only calls :class:`LeafEngine`'s methods
and never asks which engine it has; each engine owns its evidence type and its
record in the map file. :func:`octolgp.engines.engine_for` picks the engine of a
config.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf, LeafEvidence
from octolgp.scan import FloatArray, Scan
from octolgp.training import IntArray

PRUNE_FREE = 0.1192
"""A leaf all of whose voxels read below this P(occupied) is pruned to one value
(OctoMap's lower clamping bound)."""

PRUNE_OCCUPIED = 0.971
"""A leaf all of whose voxels read above this P(occupied) is pruned to one value
(OctoMap's upper clamping bound)."""

Lookup = Callable[[int], Leaf | None]
"""The current leaf of a packed key, or ``None`` (engines only read the store)."""


@dataclass(frozen=True)
class Evidence:
    """The evidence one step brings to the leaves.

    Attributes
    ----------
    changed : list of (int, Leaf)
        Leaves whose GP inputs changed, as new leaves (packed key, leaf), in key order.
    touched : list of int
        Packed keys of every leaf the step's evidence reached, ascending.
    new_items : int
        Training inputs of the changed leaves' GPs added (or forgotten).
    kept : list of (int, Leaf)
        Leaves whose evidence moved without changing what their GP sees; stored as
        they are, not refitted.
    fresh : ndarray of bool, shape (len(changed), tiles per leaf), or None
        Per changed leaf, the parts of its GP (an engine's tiles) whose stored values
        are those of its new evidence already, which :meth:`LeafEngine.fit` may keep;
        ``None``: none.
    """

    changed: list[tuple[int, Leaf]]
    touched: list[int]
    new_items: int
    kept: list[tuple[int, Leaf]] = field(default_factory=list)
    fresh: NDArray[np.bool_] | None = None


@dataclass(frozen=True, slots=True)
class LeafFit:
    """A fitted leaf and what its fit needed.

    Attributes
    ----------
    leaf : Leaf
        The leaf with fresh voxel values.
    repaired : int
        Kernel matrices of this fit that needed a jitter.
    """

    leaf: Leaf
    repaired: int


class LeafEngine(Protocol):
    """What the online map needs of a leaf engine.

    Every method is a pure function of its arguments and the engine's frozen config,
    except that an engine may keep a cache that never changes a result.
    """

    name: str
    config: MapConfig
    grid: LeafGrid

    def evidence(
        self, scans: list[Scan], lookup: Lookup, stats: dict[str, float], *, fresh: bool = True
    ) -> Evidence:
        """Scans (in time order) → the leaves they change, as new leaves.

        ``stats["training"]`` and ``stats["assign"]`` accumulate the seconds of making
        the step's observations and of assigning them to leaves. ``fresh``: whether to
        work out :attr:`Evidence.fresh` (a map that fits later refits leaves whole).
        """
        ...

    def fit(
        self,
        leaves: list[Leaf],
        hp: Hyperparameters,
        pool: Executor | None = None,
        *,
        reuse: bool = True,
        fresh: NDArray[np.bool_] | None = None,
    ) -> list[LeafFit]:
        """Fit leaves on their evidence and predict their voxels (one per leaf, in order).

        ``pool``: threads to fit on (BLAS limits are the caller's). ``reuse``: whether
        the engine may keep and reuse work of earlier fits (never a different result).
        ``fresh``: :attr:`Evidence.fresh` of these leaves, parts whose values may be kept.
        """
        ...

    def rebuilt(self, keys: Iterable[int]) -> None:
        """Say that these leaves' evidence was rebuilt, not extended (a correction)."""
        ...

    def empty(self, dim: int) -> LeafEvidence:
        """The evidence of a leaf that has seen nothing."""
        ...

    values_from_evidence: bool
    """Whether a leaf's voxel values are a cheap, deterministic function of its evidence
    (the map file then keeps the evidence only and a leaf read back is fitted again)."""

    def record(self, evidence: LeafEvidence, index: IntArray) -> bytes:
        """The evidence of the leaf ``index`` as the map file keeps it (:meth:`from_record`)."""
        ...

    def records(self, evidence: Sequence[LeafEvidence], indices: IntArray) -> list[bytes]:
        """:meth:`record` of many leaves (``indices``: (L, d)), the same bytes."""
        ...

    def from_record(self, blob: bytes, index: IntArray) -> LeafEvidence:
        """Inverse of :meth:`record`; raises ``OctolgpError`` on a corrupt blob."""
        ...

    def encode(self, evidence: LeafEvidence) -> bytes:
        """The evidence in the full-precision form of map files up to version 4."""
        ...

    def decode(self, blob: bytes, dim: int) -> LeafEvidence:
        """Inverse of :meth:`encode`; raises ``OctolgpError`` on a corrupt blob."""
        ...


@contextmanager
def stage(stats: dict[str, float], name: str) -> Iterator[None]:
    """Add the seconds the block takes to ``stats[name]`` (a step's stage timings)."""
    t = time.perf_counter()
    try:
        yield
    finally:
        stats[name] = stats.get(name, 0.0) + time.perf_counter() - t


def evidence_arrays(evidence: LeafEvidence) -> tuple[np.ndarray, ...]:
    """Every array of an engine's evidence, in field order (for comparisons and tests)."""
    return tuple(np.asarray(getattr(evidence, f.name)) for f in dataclasses.fields(evidence))  # type: ignore[arg-type]


def with_values(
    leaf: Leaf, mean: FloatArray, var: FloatArray, prob: FloatArray, prune: bool
) -> Leaf:
    """The leaf with fresh voxel values, pruned to one value where it is confident.

    A leaf whose voxels all read below :data:`PRUNE_FREE` or all above
    :data:`PRUNE_OCCUPIED` keeps one value, its least confident one, so a pruned leaf
    never overstates.
    """
    if prune and (prob.max() < PRUNE_FREE or prob.min() > PRUNE_OCCUPIED):
        at = int(np.argmax(prob) if prob.max() < PRUNE_FREE else np.argmin(prob))
        mean, var, prob = mean[at : at + 1], var[at : at + 1], prob[at : at + 1]
        pruned = True
    else:
        pruned = False
    return leaf.evolve(
        mean=mean.astype(np.float32),
        var=var.astype(np.float32),
        prob=prob.astype(np.float32),
        pruned=pruned,
        refits=leaf.refits + 1,
        pending=False,
        fitted=True,
    )


def fitted_leaves(
    leaves: list[Leaf], mean: FloatArray, var: FloatArray, prob: FloatArray, prune: bool
) -> list[Leaf]:
    """Many leaves with fresh voxel values at once: :func:`with_values` row by row.

    Parameters
    ----------
    leaves : list of Leaf
    mean, var, prob : ndarray of shape (len(leaves), V)
        Latent mean, latent variance and P(occupied) of each leaf's voxels.
    prune : bool

    Returns
    -------
    list of Leaf
        Equal to ``[with_values(leaf, mean[j], var[j], prob[j], prune) ...]``; each
        leaf owns its arrays (no view keeps the others' rows alive).
    """
    n = len(leaves)
    if not n:
        return []
    rows = np.arange(n)
    top, low = prob.max(axis=1), prob.min(axis=1)
    free, occupied = top < PRUNE_FREE, low > PRUNE_OCCUPIED
    pruned = (free | occupied) if prune else np.zeros(n, dtype=bool)
    at = np.where(free, np.argmax(prob, axis=1), np.argmin(prob, axis=1))
    values = [np.asarray(a, dtype=np.float32) for a in (mean, var, prob)]
    full = [list(v) for v in values]  # each leaf's rows, as views
    # the least confident value of each leaf, as a view of shape (1,)
    one = [list(v[rows, at][:, None]) for v in values]
    out = []
    for leaf, p, m, v, q, m1, v1, q1 in zip(leaves, pruned.tolist(), *full, *one, strict=True):
        if p:  # one iteration per leaf: copies of its rows, its own arrays
            out.append(leaf.refitted(m1.copy(), v1.copy(), q1.copy(), True))
        else:
            out.append(leaf.refitted(m.copy(), v.copy(), q.copy(), False))
    return out


def read_arrays(blob: bytes, offset: int, specs: list[tuple[int, str]]) -> list[np.ndarray]:
    """Arrays stored back to back in ``blob`` from ``offset``, which must end the blob.

    ``specs`` gives each array's element count and little-endian dtype; the arrays are
    returned in native byte order, as copies.

    Raises
    ------
    OctolgpError
        If the blob is not exactly that long.
    """
    need = offset + sum(n * np.dtype(t).itemsize for n, t in specs)
    if len(blob) != need:
        raise OctolgpError(f"leaf record has {len(blob)} bytes, expected {need}")
    out = []
    for n, t in specs:  # one array per spec
        arr = np.frombuffer(blob, dtype=t, count=n, offset=offset)
        out.append(arr.astype(np.dtype(t).newbyteorder("=")))
        offset += n * arr.itemsize
    return out
