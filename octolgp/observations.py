"""Scan → voxel observations: which voxels each scan saw occupied and which it saw free.

The training data of the lattice leaf engine (:mod:`octolgp.gp.lattice`), the
voxel-level form of :mod:`octolgp.training`'s rule: a beam's hit is an observation
"occupied" of the voxel holding it; its free segment (stopping ``free_margin`` short of
the hit, or at ``max_range`` for a no-return) is an observation "free" of every voxel
it passes through: every voxel the closed segment from the sensor to the segment's end
meets, the voxels of :func:`octolgp.geometry.raycast.traverse_voxels` (OctoMap's
``computeRayKeys``) and the end's own voxel, found exactly by the segment's border
crossings.

Within one scan each voxel counts once per class, and a voxel holding a return of
the scan is not also free in that scan (OctoMap's discretised insertion). Across
scans the counts add: ``hits[v]`` is the number of scans with a return in ``v``,
``frees[v]`` the number whose free segments cross ``v`` without a return there. The
counts of a set of scans are therefore the sums of the counts of its parts, in any
order: this is what makes inserting scans one by one equal to inserting them at once.

**Newer evidence wins** (``OnlineConfig.clear_scans`` = K > 0, the default): a voxel's
state is its return count and its free count since its last return, and each scan
changes it by :func:`newer_evidence_wins`: a return counts and restarts the free count,
a free look counts up to K, and K free looks forget the returns. That function is the
rule's specification. To apply a whole run of scans at once, its observations are
summarised per voxel (:class:`VoxelObservations`' ``head_frees``, ``tail_frees`` and
``restart_*``) so that :func:`advance` gives what the scans one by one would; summaries
of consecutive runs compose (:func:`merge_observations`), so one-by-one and one-step
insertion agree (``tests/test_observations.py`` checks :func:`advance` against
:func:`newer_evidence_wins`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.config import MapConfig
from octolgp.geometry import merge_kernel, ray_kernel
from octolgp.geometry.keys import (
    KEY_BITS,
    KeyRegion,
    pack_keys,
    return_steps,
    step_points,
    unpack_keys,
)
from octolgp.scan import Scan
from octolgp.training import Beams, IntArray, check_scans, config_beams, stack_beams

BLOCK_VOXELS = 1 << 18
"""Voxels of free segments (their origins' and one per border crossing) handled at once
(bounds the transient arrays)."""

DENSE_CELLS = 1 << 25
"""Most cells of the per-scan key boxes deduplicated in a dense map (a byte each)
rather than by sorting."""

DENSE_PER_VOXEL = 64
"""... and most of those cells per voxel visited (a sparse box sorts faster)."""

TIE_BAND = 1e-7
"""Distance, in voxels, from a border within which a crossing's order is decided exactly."""

MAX_SCANS = 1 << 12
"""Scans whose observations are deduplicated in one pass (the scan number shares an
int64 with the packed voxel key)."""


@dataclass(frozen=True)
class VoxelObservations:
    """Observation counts per voxel.

    Attributes
    ----------
    keys : ndarray of int64, shape (n, d)
        OctoMap keys of the observed voxels, unique, ascending by packed key.
    hits : ndarray of int64, shape (n,)
        Scans with a return in the voxel.
    frees : ndarray of int64, shape (n,)
        Scans whose free segments cross the voxel and hold no return in it.
    weak_frees : ndarray of int64, shape (n,)
        Those of them whose free segments cross it only within ``clear_margin`` of their
        return (a beam grazing a wall) or only on no-return beams (a dark or glass
        surface also gives none): free evidence, but with newer evidence winning they do
        not count towards forgetting a return. Zeros when ``clear_scans`` is 0.
    first_hit : ndarray of shape (n, d)
        The first return in the voxel (scan order, then beam order), metres, world
        frame; NaN where ``hits`` is 0.
    clear_scans : int
        The K of the newer-evidence rule the summary below was made for; 0: static
        (the summary is then ``frees``, ``frees``, zeros and NaN, and unused).
    head_frees, tail_frees : ndarray of int64, shape (n,)
        Scans seeing the voxel free (not only weakly) before its first return and
        after its last return (both ``frees - weak_frees`` where ``hits`` is 0).
    restart_hits : ndarray of int64, shape (n,)
        Where a run of at least K scans seeing the voxel (not only weakly) free lies
        between two of its
        returns: the returns from the first one after the last such run on (their
        predecessors are forgotten); else 0.
    restart_hit : ndarray of shape (n, d)
        The first return of the scan that starts ``restart_hits``; NaN where it is 0.
    chord : ndarray of int64, shape (n, c), optional
        Chord weights (``LatticeConfig.free_evidence = "chord"``), for the ``c`` free
        looks a voxel's free count counts (:func:`chord_looks`): ``chord[i, m - 1]`` is
        the sum, over the first ``m`` scans seeing voxel ``i`` free, of their free
        segments' shares of their chords through the box of :data:`CHORD_BOX` keys
        holding it (:func:`_walk_free`), in ``ray_kernel.CHORD_UNITS`` (the total where
        fewer scans saw it free). ``None``: not observed.
    strong_chord : ndarray of int64, shape (n, c), optional
        The same over the scans seeing the voxel free that count towards forgetting
        (not only weakly).
    tail_chord : ndarray of int64, shape (n,), optional
        The same over the first ``c`` of those after the voxel's last return (from the
        run's start where ``hits`` is 0). Zeros when ``clear_scans`` is 0.
    """

    keys: IntArray
    hits: IntArray
    frees: IntArray
    weak_frees: IntArray
    first_hit: np.ndarray
    clear_scans: int
    head_frees: IntArray
    tail_frees: IntArray
    restart_hits: IntArray
    restart_hit: np.ndarray
    chord: IntArray | None = None
    strong_chord: IntArray | None = None
    tail_chord: IntArray | None = None

    @property
    def strong_frees(self) -> IntArray:
        """Scans seeing the voxel free that count towards forgetting its returns."""
        out: IntArray = self.frees - self.weak_frees
        return out

    @property
    def n_voxels(self) -> int:
        """Observed voxels."""
        return int(self.hits.size)


def _distinct(a: IntArray) -> IntArray:
    """The distinct values of a sorted array."""
    if a.size == 0:
        return a
    keep = np.empty(a.size, dtype=bool)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    out: IntArray = a[keep]
    return out


def sorted_unique(values: IntArray) -> IntArray:
    """``np.unique`` of an int64 array by one sort (numpy's hash-based unique is slower here)."""
    return _distinct(np.sort(values, kind="stable" if values.size < 64 else "quicksort"))


def sorted_contains(sorted_values: IntArray, queries: IntArray) -> NDArray[np.bool_]:
    """Whether each query occurs in an ascending array (a binary search per query)."""
    if sorted_values.size == 0:
        return np.zeros(queries.shape, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_values, queries), sorted_values.size - 1)
    found: NDArray[np.bool_] = sorted_values[at] == queries
    return found


def merge_unique(*runs: IntArray) -> IntArray:
    """The sorted unique values of ascending int64 arrays (a stable sort merges the runs)."""
    return _distinct(np.sort(np.concatenate([np.zeros(0, dtype=np.int64), *runs]), kind="stable"))


def _unique_counts(values: IntArray, ascending: bool = False) -> tuple[IntArray, IntArray]:
    """Sorted unique values and how often each occurs (``ascending``: already sorted)."""
    a = values if ascending else np.sort(values)
    if a.size == 0:
        return a, np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, a[1:] != a[:-1]])
    return a[starts], np.diff(np.r_[starts, a.size]).astype(np.int64)


def _voxel_keys(points: np.ndarray, resolution: float, tree_depth: int) -> IntArray:
    """OctoMap keys of points known to be addressable (no range check), (n, d)."""
    keys: IntArray = np.floor(points / resolution).astype(np.int64) + (1 << (tree_depth - 1))
    return keys


def _scan_codes(packed: IntArray, scan: IntArray, dim: int) -> IntArray:
    """One int64 per (scan, voxel): the scan number above the packed key's bits."""
    out: IntArray = packed | (scan << (KEY_BITS * dim))
    return out


def _box_codes(
    cell: IntArray, base: IntArray, stride: IntArray, low: IntArray, scans: IntArray, dim: int
) -> IntArray:
    """(scan, voxel) codes of cells of per-scan key boxes laid end to end.

    Parameters
    ----------
    cell : ndarray of int64, shape (m,)
        Cells, ascending, each below ``DENSE_CELLS``.
    base : ndarray of int64, shape (s,)
        Each scan's first cell, ascending.
    stride : ndarray of int64, shape (s, d)
        Cells per step along each axis in each scan's box (1 along the first axis).
    low : ndarray of int64, shape (s, d)
        Each box's least key per axis.
    scans : ndarray of int64, shape (s,)
        The boxes' scan numbers.
    dim : int

    Returns
    -------
    ndarray of int64, shape (m,)
        The codes, ascending.
    """
    first = np.searchsorted(cell, base)
    s = np.repeat(np.arange(base.size), np.diff(np.r_[first, cell.size]))
    shift = KEY_BITS * np.arange(dim)
    corner = (scans << (KEY_BITS * dim)) | (low << shift).sum(axis=1)
    code = corner[s]
    # exact in float64: cells and strides are integers below 2**25 (DENSE_CELLS)
    local = (cell - base[s]).astype(float)
    for a in range(dim - 1, 0, -1):  # one pass per axis, the slowest first
        step = stride[:, a].astype(float)[s]
        along = np.floor(local / step)
        local -= along * step
        code += along.astype(np.int64) << shift[a]
    out: IntArray = code + local.astype(np.int64)
    return out


def _steps_before(
    t: np.ndarray,
    seg: IntArray,
    a: int,
    b: int,
    crossings: IntArray,
    frac: np.ndarray,
    du: np.ndarray,
    gap: np.ndarray,
) -> np.ndarray:
    """Signed steps along axis ``b`` before each crossing of axis ``a`` (``a != b``).

    A crossing of ``b`` comes first if its ``t`` is smaller, or equal and ``b > a``.

    Parameters
    ----------
    t : ndarray of shape (c,)
        The crossings of ``a``: parameter along their segment, 0 at its origin, 1 at
        its end.
    seg : ndarray of int64, shape (c,)
        Their segments.
    a, b : int
        The axes.
    crossings : ndarray of int64, shape (b,)
        Per segment, borders of ``b`` crossed.
    frac, du : ndarray of shape (b,)
        Per segment, along ``b`` in voxels: the origin's offset in its voxel, in
        ``[0, 1)``, and the change from origin to end.
    gap : ndarray of shape (b,)
        Per segment, ``t`` of the ``i``-th border of ``b`` times ``|du|``, less ``i``.

    Returns
    -------
    ndarray of float, shape (c,)
        Whole numbers: the key change along ``b`` from the origin's voxel.
    """
    w = frac[seg] + t * du[seg]  # along b, in voxels from the origin voxel's low border
    steps: np.ndarray = np.floor(w)
    r = w - steps
    close = np.flatnonzero((r < TIE_BAND) | (r > 1.0 - TIE_BAND))
    if close.size:  # near a border of b: compare the two crossings' t
        s = seg[close]
        nearest = np.rint(w[close])
        forward = du[s] > 0
        j = np.where(forward, nearest, 1.0 - nearest)  # that border's number along b
        with np.errstate(divide="ignore", invalid="ignore"):
            t_b = (j - gap[s]) / np.abs(du[s])
        t_a = t[close]
        first = (t_b < t_a) | ((t_b == t_a) & (b > a))
        first &= (j >= 1) & (j <= crossings[s])
        count = np.clip(j - 1 + first, 0, crossings[s])
        steps[close] = np.where(forward, count, -count)
    return steps


def _first_of_each(values: IntArray) -> IntArray:
    """Indices of each distinct value's first occurrence, ordered by value."""
    order = np.argsort(values, kind="stable")
    if order.size == 0:
        return order
    ordered = values[order]
    first: IntArray = order[np.r_[True, ordered[1:] != ordered[:-1]]]
    return first


def _segment_crossings(
    origins: np.ndarray, free_end: np.ndarray, resolution: float, tree_depth: int
) -> tuple[IntArray, IntArray, np.ndarray, IntArray, np.ndarray, np.ndarray]:
    """Each segment's voxel walk, per axis, in voxels: what both walks start from.

    Returns
    -------
    key0, key1 : ndarray of int64, shape (b, d)
        The keys of the origin's and the end's voxels.
    du : ndarray of shape (b, d)
        The change from origin to end.
    crossings : ndarray of int64, shape (b, d)
        Voxel borders crossed.
    frac : ndarray of shape (b, d)
        The origin's offset in its voxel, in ``[0, 1)``.
    gap : ndarray of shape (b, d)
        The origin's distance to the first border crossed: border ``i`` at
        ``t = (i - gap) / |du|``.
    """
    u0 = origins / resolution  # coordinates in voxels
    k0 = np.floor(u0)
    k1 = np.floor(free_end / resolution)
    du = free_end / resolution - u0
    crossings = np.abs(k1 - k0).astype(np.int64)
    frac = u0 - k0
    gap = np.where(du < 0, 1.0 - frac, frac)
    offset = 1 << (tree_depth - 1)
    return k0.astype(np.int64) + offset, k1.astype(np.int64) + offset, du, crossings, frac, gap


def _near_ends(beams: Beams, config: MapConfig) -> np.ndarray | None:
    """Per free segment, metres before its end within which a free look is weak.

    Within ``clear_margin`` of the beam's return, or anywhere on a no-return beam; ``None``
    without forgetting (``clear_scans`` 0), where no look is weak.
    """
    if not config.clear_scans:
        return None
    margin = max(config.clear_margin - config.free_margin, 0.0)  # from the segment's end
    near: np.ndarray = np.where(beams.is_hit[beams.has_seg], margin, np.inf)
    return near


def _enter_near(near: np.ndarray, origins: np.ndarray, free_end: np.ndarray) -> np.ndarray:
    """Per segment, the ``t`` from which a voxel entered is within ``near`` of its end."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out: np.ndarray = 1.0 - near / np.linalg.norm(free_end - origins, axis=1)
    return out


def _free_codes(
    origins: np.ndarray,
    free_end: np.ndarray,
    scan: IntArray,
    resolution: float,
    tree_depth: int,
    near: np.ndarray | None = None,
    *,
    compiled: bool | None = None,
    region: KeyRegion | None = None,
) -> tuple[IntArray, IntArray]:
    """Unique (scan, voxel) codes of the voxels the free segments pass through.

    :func:`_walk_free` without chord shares: its ``codes`` and ``near_only``.
    """
    codes, near_only, _ = _walk_free(
        origins, free_end, scan, resolution, tree_depth, near, compiled=compiled, region=region
    )
    return codes, near_only


def _visit_shares(
    owner: IntArray, t: np.ndarray, axis: IntArray, leaves: NDArray[np.bool_]
) -> IntArray:
    """Chord shares of segments' voxel visits, as the compiled walk computes them.

    Parameters
    ----------
    owner : ndarray of int64, shape (m,)
        Each visit's segment.
    t : ndarray of shape (m,)
        Where the segment enters the voxel (0 for its origin's).
    axis : ndarray of int64, shape (m,)
        The axis crossed to enter it (the dimension for the origin's voxel): visits at
        equal ``t`` go in the walk's order, the last axis first.
    leaves : ndarray of bool, shape (m,)
        The crossing enters another box.

    Returns
    -------
    ndarray of int64, shape (m,)
        Each visit's share of its segment's chord through its box, in
        ``ray_kernel.CHORD_UNITS`` (rounded to nearest, at least 1).
    """
    if owner.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((-axis, t, owner))  # the walk's order
    o, tt = owner[order], t[order]
    last = np.r_[o[1:] != o[:-1], True]  # a segment's last visit
    t_next = np.where(last, 1.0, np.r_[tt[1:], 1.0])  # where the walk leaves the voxel
    run_start = np.r_[True, (o[1:] != o[:-1]) | leaves[order][1:]]  # a box's first visit
    run = np.cumsum(run_start) - 1
    run_last = np.r_[run_start[1:], True]
    total = t_next[run_last][run] - tt[run_start][run]
    count = np.bincount(run)[run]
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(total > 0.0, (t_next - tt) / total, 1.0 / count)
    q = np.maximum(1, np.floor(share * ray_kernel.CHORD_UNITS + 0.5)).astype(np.int64)
    out = np.empty(owner.size, dtype=np.int64)
    out[order] = q
    return out


def _code_sums(codes: IntArray, values: IntArray) -> tuple[IntArray, IntArray]:
    """Sorted unique codes and the sum of ``values`` over each code's occurrences."""
    order = np.argsort(codes, kind="stable")
    c = codes[order]
    if c.size == 0:
        return c, np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    return c[starts], np.add.reduceat(values[order].astype(np.int64), starts)


def _walk_free(
    origins: np.ndarray,
    free_end: np.ndarray,
    scan: IntArray,
    resolution: float,
    tree_depth: int,
    near: np.ndarray | None = None,
    *,
    compiled: bool | None = None,
    region: KeyRegion | None = None,
    box: int = 0,
) -> tuple[IntArray, IntArray, IntArray]:
    """Unique (scan, voxel) codes of the voxels the free segments pass through, and their shares.

    A segment's voxels are every voxel the closed segment from its origin to its end
    passes through: those of :func:`octolgp.geometry.raycast.traverse_voxels` (OctoMap's
    ``computeRayKeys``) and the end's own voxel. Per axis a segment crosses
    ``|floor(end / r) - floor(origin / r)|`` voxel borders; the ``i``-th at parameter
    ``t = (i - g) / |Δu|`` (``u`` the coordinate in voxels, ``g`` the origin's distance
    to the first border, ``t`` 0 at the origin and 1 at the end). Its voxels are the
    origin's and, per crossing, the voxel it enters: on the crossing's axis one step
    further, on each other axis the voxel the segment is in at that ``t``. Crossings at
    equal ``t`` (through an edge or corner) go in traverse_voxels' order, the last axis
    first; a crossing within ``TIE_BAND`` voxels of another axis's border has its order
    decided on the computed ``t`` of both, so the voxels always form one face-connected
    path from the origin's voxel to the end's.

    Parameters
    ----------
    origins, free_end : ndarray of shape (b, d)
        Segment starts and ends, world frame, metres (addressable).
    scan : ndarray of int64, shape (b,)
        Each segment's scan number, ``0 <= scan < MAX_SCANS``.
    resolution : float
        Voxel edge, metres.
    tree_depth : int
        OctoMap key depth.
    near : ndarray of shape (b,), optional
        Per segment, metres before its end (``inf``: all of it).
    compiled : bool, optional
        Walk the segments with the compiled loop (:mod:`octolgp.geometry.ray_kernel`)
        or compute the crossings with numpy; by default compiled where numba imports.
        Both give the same codes.
    region : KeyRegion, optional
        Keep only the voxels in it (dropped as they are walked); all where ``None``.
    box : int
        With ``box > 0``, each segment gives every voxel it passes through the voxel's
        share of its chord through the box of ``box`` keys per axis (aligned to key 0,
        a leaf's) holding the voxel (:func:`octolgp.geometry.ray_kernel.walk_segments`),
        summed per (scan, voxel); ``0``: no shares.

    Returns
    -------
    codes : ndarray of int64, shape (m,)
        Every (scan, voxel) code a segment passes through, ascending.
    near_only : ndarray of int64, shape (k,)
        Those whose every segment of that scan is within ``near`` of its end inside
        the voxel: the segment enters the voxel at ``t >= 1 - near / length``
        (``length`` the segment's, metres). Empty where ``near`` is None.
    shares : ndarray of int64, shape (m,) or (0,)
        Each code's summed chord shares in ``ray_kernel.CHORD_UNITS`` (empty where
        ``box`` is 0).
    """
    none = np.zeros(0, dtype=np.int64)
    n_seg, dim = origins.shape
    if n_seg == 0:
        return none, none, none
    key0, key1, du, crossings, frac, gap = _segment_crossings(
        origins, free_end, resolution, tree_depth
    )
    step = np.where(du < 0, -1, 1)
    scans, which = np.unique(scan, return_inverse=True)
    low = np.full((scans.size, dim), np.iinfo(np.int64).max)
    high = np.full((scans.size, dim), np.iinfo(np.int64).min)
    np.minimum.at(low, which, np.minimum(key0, key1))
    np.maximum.at(high, which, np.maximum(key0, key1))
    extent = high - low + 1  # (s, d) each scan's box of keys
    cells = np.prod(extent, axis=1)
    per_seg = crossings.sum(axis=1) + 1  # voxels per segment
    dense = bool(cells.sum() <= min(DENSE_CELLS, DENSE_PER_VOXEL * int(per_seg.sum())))
    if dense:  # an index into the scans' boxes laid end to end, ascending as the codes
        base = np.cumsum(cells) - cells
        box_stride = np.cumprod(np.c_[np.ones(scans.size, np.int64), extent[:, :-1]], axis=1)
        stride = box_stride[which]
        start = base[which] + ((key0 - low[which]) * stride).sum(axis=1)
    else:  # the codes themselves
        stride = np.broadcast_to(np.int64(1) << (KEY_BITS * np.arange(dim)), (n_seg, dim))
        start = (scan << (KEY_BITS * dim)) | (key0 << (KEY_BITS * np.arange(dim))).sum(axis=1)
    if near is not None:
        enter_near = _enter_near(near, origins, free_end)
    columns = [
        [np.ascontiguousarray(x[:, a]) for a in range(dim)]
        for x in (crossings, frac, du, np.abs(du), gap, (step * stride).astype(float))
    ]
    n_c, frac_c, du_c, size_c, gap_c, move_c = columns
    stride_c = [np.ascontiguousarray(stride[:, a]).astype(float) for a in range(dim)]
    if compiled is None:
        compiled = ray_kernel.AVAILABLE
    state = ray_kernel.state_map(int(cells.sum()) if dense else 0)
    weights = np.zeros(state.size if box and dense else 0, dtype=np.int32)
    share_codes: list[IntArray] = []  # sparse: every visit's code and share
    share_parts: list[IntArray] = []
    parts: list[IntArray] = []
    near_parts: list[IntArray] = []
    ends = np.cumsum(per_seg)
    if compiled:
        move = step * stride
        size = np.abs(du)
        enter = enter_near if near is not None else np.full(n_seg, np.inf)
    lo = 0
    while lo < n_seg:  # blocks of about BLOCK_VOXELS voxels (all at once when compiled)
        hi = int(np.searchsorted(ends, ends[lo] - per_seg[lo] + BLOCK_VOXELS, side="right"))
        hi = n_seg if compiled and dense else max(hi, lo + 1)
        if compiled:  # the compiled walk marks the maps, or lists the block's voxels
            s = slice(lo, hi)
            listed, listed_near, listed_share = ray_kernel.walk_segments(
                start[s],
                move[s],
                crossings[s],
                gap[s],
                size[s],
                enter[s],
                state if dense else None,
                (key0[s], box, weights if dense else None) if box else None,
            )
            if not dense:
                if region is not None:
                    walked = region.contains(listed)
                    listed, listed_near = listed[walked], listed_near[walked]
                    if box:
                        listed_share = listed_share[walked]
                if box:
                    share_codes.append(listed)
                    share_parts.append(listed_share)
                if near is not None:
                    near_parts.append(sorted_unique(listed[listed_near]))
                parts.append(sorted_unique(listed[~listed_near]))
            lo = hi
            continue
        index = [start[lo:hi]]  # each segment's origin voxel, entered at t = 0
        t_in = [np.zeros(hi - lo)]
        owner = [np.arange(lo, hi)]
        axes = [np.full(hi - lo, dim, dtype=np.int64)]
        leaves = [np.zeros(hi - lo, dtype=bool)]
        for a in range(dim):  # the crossings of axis a
            counts = n_c[a][lo:hi]
            total = int(counts.sum())
            if total == 0:
                continue
            seg = np.repeat(np.arange(lo, hi), counts)
            i = np.arange(1, total + 1) - np.repeat(np.cumsum(counts) - counts, counts)
            t = (i - gap_c[a][seg]) / size_c[a][seg]
            if box:  # the crossing enters another box along a
                after = key0[seg, a] + i * step[seg, a]
                leaves.append(after // box != (after - step[seg, a]) // box)
                axes.append(np.full(total, a, dtype=np.int64))
            moved = i * move_c[a][seg]  # index change from the origin's voxel
            for b in range(dim):  # the other axes: their voxel at t
                if b != a:
                    steps = _steps_before(t, seg, a, b, n_c[b], frac_c[b], du_c[b], gap_c[b])
                    moved += steps * stride_c[b][seg]
            index.append(start[seg] + moved.astype(np.int64))
            t_in.append(t)
            owner.append(seg)
        idx = np.concatenate(index)
        wanted = None if dense or region is None else region.contains(idx)
        if box:
            q = _visit_shares(
                np.concatenate(owner),
                np.concatenate(t_in),
                np.concatenate(axes),
                np.concatenate(leaves),
            )
            if dense:
                np.add.at(weights, idx, q.astype(np.int32))
            else:
                share_codes.append(idx if wanted is None else idx[wanted])
                share_parts.append(q if wanted is None else q[wanted])
        if near is not None:
            is_near = np.concatenate(t_in) >= enter_near[np.concatenate(owner)]
            if wanted is not None:
                is_near = is_near[wanted]
        if wanted is not None:
            idx = idx[wanted]
        if near is not None:
            if dense:
                state[idx[is_near]] |= ray_kernel.NEAR
            else:
                near_parts.append(sorted_unique(idx[is_near]))
            idx = idx[~is_near]
        if dense:
            state[idx] |= ray_kernel.FAR
        else:
            parts.append(sorted_unique(idx))
        lo = hi
    if dense:
        visits = int(per_seg.sum())
        cell = ray_kernel.marked_cells(state, visits) if compiled else np.flatnonzero(state != 0)
        codes = _box_codes(cell, base, box_stride, low, scans, dim)
        if region is not None:
            marked = region.contains(codes)
            cell, codes = cell[marked], codes[marked]
        shares = weights[cell].astype(np.int64) if box else none
        if near is None:
            return codes, none, shares
        return codes, codes[state[cell] == ray_kernel.NEAR], shares
    shares = none
    if box:
        _, shares = _code_sums(
            np.concatenate([none, *share_codes]), np.concatenate([none, *share_parts])
        )
    far = merge_unique(*parts)
    if near is None:
        return far, none, shares
    close_codes = merge_unique(*near_parts)
    only = close_codes[~np.isin(close_codes, far, assume_unique=True)]
    return merge_unique(far, only), only, shares


def observe(
    scans: Iterable[Scan],
    config: MapConfig,
    region: KeyRegion | None = None,
    *,
    compiled: bool | None = None,
) -> VoxelObservations:
    """Count, per voxel, the scans that saw it occupied and the scans that saw it free.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim`` (points addressable), in time
        order.
    config : MapConfig
        Uses ``resolution``, ``tree_depth``, ``free_margin`` and ``clear_scans``.
    region : KeyRegion, optional
        Observe only the voxels in it: the result is the whole one's voxels in the
        region, exactly (every count is per voxel). All voxels where ``None``.
    compiled : bool, optional
        Walk the free segments with the compiled loop, and observe one scan (without a
        region) in one pass over a map of its voxels (:func:`_observe_one`); or do it
        all with numpy. By default compiled where numba imports. Both give the same
        observations.

    Returns
    -------
    VoxelObservations

    Raises
    ------
    OctolgpError
        On an empty sequence or a dimension mismatch.
    """
    scan_list = check_scans(scans, config.dim)
    if len(scan_list) > MAX_SCANS:
        parts = [
            observe(scan_list[lo : lo + MAX_SCANS], config, region, compiled=compiled)
            for lo in range(0, len(scan_list), MAX_SCANS)
        ]
        return merge_observations(parts, config.dim)
    dim, res, depth = config.dim, config.resolution, config.tree_depth
    origins, ends, max_range = stack_beams(scan_list)
    beams = config_beams(origins, ends, max_range, config)
    if compiled is None:
        compiled = ray_kernel.AVAILABLE
    if compiled and len(scan_list) == 1 and region is None:
        single = _observe_one(origins, ends, beams, config)
        if single is not None:
            return single
    scan = np.repeat(np.arange(len(scan_list), dtype=np.int64), [len(s) for s in scan_list])
    returns, hit_scan = ends[beams.is_hit], scan[beams.is_hit]
    hit_keys = _voxel_keys(returns, res, depth)
    hit_packed = pack_keys(hit_keys)
    if region is not None:
        held = region.contains(hit_packed)
        returns, hit_scan, hit_keys, hit_packed = (
            returns[held],
            hit_scan[held],
            hit_keys[held],
            hit_packed[held],
        )
    # returns at the precision a map file keeps them (a map equals the map read back)
    hit_points = step_points(return_steps(returns, hit_keys, res, depth), hit_keys, res, depth)
    # one (scan, voxel) code per return; the first return of each, in beam order
    all_codes = _scan_codes(hit_packed, hit_scan, dim)
    first_of_code = _first_of_each(all_codes)
    hit_codes = all_codes[first_of_code]
    code_points = hit_points[first_of_code]
    seg = beams.has_seg
    k = config.clear_scans
    near = _near_ends(beams, config)
    box = chord_box(config)
    free_codes, weak_codes, shares = _walk_free(
        origins[seg],
        beams.free_end[seg],
        scan[seg],
        res,
        depth,
        near,
        compiled=compiled,
        region=region,
        box=box,
    )
    seen_free = ~sorted_contains(hit_codes, free_codes)  # both ascending
    free_codes = free_codes[seen_free]
    if box:
        shares = shares[seen_free]
    weak_codes = weak_codes[~sorted_contains(hit_codes, weak_codes)]
    mask = (1 << (KEY_BITS * dim)) - 1
    one = len(scan_list) == 1  # codes of one scan ascend as their voxels do
    hit_vox, hit_n = _unique_counts(hit_codes & mask, one)
    free_vox, free_n = _unique_counts(free_codes & mask, one)
    weak_vox, weak_n = _unique_counts(weak_codes & mask, one)
    # the first return per voxel: codes ascend by scan, a stable sort keeps that order
    first = _first_of_each(hit_codes & mask)
    obs = _combine(hit_vox, hit_n, free_vox, free_n, code_points[first], dim)
    # which free looks count towards forgetting (all of them without forgetting)
    strong_look = ~sorted_contains(weak_codes, free_codes) if k else None
    chord = None
    if box:
        strong_or_all = np.ones(free_codes.size, bool) if strong_look is None else strong_look
        if one:  # each voxel seen free at most once: its look is its first m, every m
            chord = _one_scan_sums(obs, free_codes & mask, shares, strong_or_all, config)
        else:
            chord = _chord_sums(obs, hit_codes, free_codes, shares, strong_or_all, config)
    if strong_look is not None:
        weak = np.zeros(obs.hits.size, dtype=np.int64)
        weak[np.searchsorted(pack_keys(obs.keys), weak_vox)] = weak_n
        obs = dataclasses.replace(obs, weak_frees=weak)
        if one:
            obs = one_scan_summary(obs, k)
        else:
            obs = _summarise(obs, hit_codes, code_points, free_codes[strong_look], k)
    if chord is not None:
        obs = dataclasses.replace(obs, chord=chord[0], strong_chord=chord[1], tail_chord=chord[2])
    return obs


CHORD_BOX = 16
"""Edge, in voxels, of the key-aligned boxes free segments' chords are shared in: the
default leaf's edge in 2D and 3D. A constant, not the leaf's edge, so that the map does
not depend on ``online.leaf_depth`` (tile-sized leaves give the map of tiled ones)."""


def chord_box(config: MapConfig) -> int:
    """Edge, in voxels, of the boxes free segments' chords are shared in (0: no shares).

    :data:`CHORD_BOX` where ``lattice.free_evidence`` is ``"chord"`` and the engine is
    the lattice engine.
    """
    if config.online.engine != "lattice" or config.free_evidence != "chord":
        return 0
    return CHORD_BOX


def chord_looks(config: MapConfig) -> int:
    """Free looks a voxel's chord sum covers: those its free count counts.

    The free count saturates at ``clear_scans`` with newer evidence winning, else at
    ``lattice.evidence_cap`` (:func:`advance`); the summed shares stop where it stops,
    so that a revisit that changes no count changes no sum (and refits nothing).
    """
    return config.clear_scans or config.lattice.evidence_cap


def _chord_sums(
    obs: VoxelObservations,
    hit_codes: IntArray,
    free_codes: IntArray,
    shares: IntArray,
    strong: NDArray[np.bool_],
    config: MapConfig,
) -> tuple[IntArray, IntArray, IntArray]:
    """Per voxel of ``obs``: ``chord``, ``strong_chord`` and ``tail_chord`` (see its fields).

    ``hit_codes`` and ``free_codes`` are the (scan, voxel) codes seen occupied and free,
    ascending, ``shares`` the free ones' summed shares and ``strong`` whether each counts
    towards forgetting.
    """
    c = chord_looks(config)
    bits = KEY_BITS * config.dim
    mask = (1 << bits) - 1
    packed = pack_keys(obs.keys)
    n = packed.size
    # the looks by voxel, then scan (the scan number fits below the voxel's bits)
    order = np.argsort(((free_codes & mask) << 12) | (free_codes >> bits))
    voxel = np.searchsorted(packed, free_codes[order] & mask)
    scan, share, strong = free_codes[order] >> bits, shares[order], strong[order]
    last_hit = np.full(n, -1, dtype=np.int64)
    np.maximum.at(last_hit, np.searchsorted(packed, hit_codes & mask), hit_codes >> bits)
    starts = np.searchsorted(voxel, np.arange(n))

    def prefix(counted: NDArray[np.bool_]) -> IntArray:
        """Per voxel, the summed shares of its first m counted looks, m = 1..c."""
        before: IntArray = np.cumsum(counted) - counted  # counted looks before each look
        rank = before - np.r_[before, 0][starts][voxel]
        use = counted & (rank < c)
        sums = np.bincount(voxel[use] * c + rank[use], share[use], minlength=n * c)
        out: IntArray = np.cumsum(sums.reshape(n, c).astype(np.int64), axis=1)
        return out

    every = prefix(np.ones(voxel.size, dtype=bool))
    strong_sums = prefix(strong)
    if not config.clear_scans:
        return every, strong_sums, np.zeros(n, dtype=np.int64)
    tail = prefix(strong & (scan > last_hit[voxel]))[:, -1]
    return every, strong_sums, tail


def _one_scan_sums(
    obs: VoxelObservations,
    free_vox: IntArray,
    shares: IntArray,
    strong: NDArray[np.bool_],
    config: MapConfig,
) -> tuple[IntArray, IntArray, IntArray]:
    """:func:`_chord_sums` of one scan, directly (:func:`_one_look_sums` per voxel).

    ``free_vox``: the packed voxels seen free, ascending, with their ``shares`` and
    whether each look is ``strong``.
    """
    n = obs.hits.size
    share = np.zeros(n, dtype=np.int64)
    at = np.searchsorted(pack_keys(obs.keys), free_vox)
    share[at] = shares
    strong_share = np.zeros(n, dtype=np.int64)
    strong_share[at[strong]] = shares[strong]
    return _one_look_sums(share, strong_share, config)


def _one_look_sums(
    share: IntArray, strong_share: IntArray, config: MapConfig
) -> tuple[IntArray, IntArray, IntArray]:
    """``chord``, ``strong_chord`` and ``tail_chord`` of voxels seen free at most once.

    In one scan a voxel is seen free at most once and never after a return of the same
    scan, so the summed shares of its first ``m`` looks are its one look's ``share`` for
    every ``m`` (the columns are views of one array), and that look, where strong, is
    the tail after its last return (``strong_share``: the share where the look is
    strong, else 0).
    """
    n, c = share.size, chord_looks(config)
    tail = strong_share if config.clear_scans else np.zeros(n, dtype=np.int64)
    return (
        np.broadcast_to(share[:, None], (n, c)),
        np.broadcast_to(strong_share[:, None], (n, c)),
        tail,
    )


def _observe_one(
    origins: np.ndarray, ends: np.ndarray, beams: Beams, config: MapConfig
) -> VoxelObservations | None:
    """One scan's observations from one map over the box of its voxels (compiled walk).

    The returns' voxels and those the free segments pass through are marked in one
    byte per cell of the box of keys holding them (``ray_kernel.HIT``, and the walk's
    ``ray_kernel.FAR`` and ``ray_kernel.NEAR``), and each voxel's counts, chord shares
    and first return are read off its cell in one compiled pass
    (``ray_kernel.read_marks``): in one scan a voxel is seen occupied (a return in it) or
    free (a segment through it, weakly where only near its return), never both, so its
    newer-evidence summary and its chord sums follow from its counts directly
    (:func:`one_scan_summary`'s). This is :func:`observe`'s general path for one scan,
    without its sorts and searches.

    Parameters
    ----------
    origins, ends : ndarray of shape (b, d)
        The scan's beams, world frame, metres (addressable).
    beams : Beams
        ``config_beams`` of them.
    config : MapConfig

    Returns
    -------
    VoxelObservations or None
        ``None`` where the box has more cells than a dense map may
        (``DENSE_CELLS``, ``DENSE_PER_VOXEL``): the general path serves.
    """
    dim, res, depth = config.dim, config.resolution, config.tree_depth
    # np.compress: the rows a mask keeps, at a third of boolean indexing's cost here
    returns = np.compress(beams.is_hit, ends, axis=0)
    hit_keys = _voxel_keys(returns, res, depth)
    seg = beams.has_seg
    start_pt, end_pt = np.compress(seg, origins, axis=0), np.compress(seg, beams.free_end, axis=0)
    key0, key1, du, crossings, _, gap = _segment_crossings(start_pt, end_pt, res, depth)
    # an axis a row: numpy reduces along contiguous rows far faster than down columns
    corners = np.concatenate([key0, key1, hit_keys]).T.copy()
    if corners.shape[1] == 0:
        return None
    low, high = corners.min(axis=1), corners.max(axis=1)
    extent = high - low + 1
    sizes = extent.tolist()
    cells = math.prod(sizes)
    visits = int(crossings.sum()) + crossings.shape[0] + hit_keys.shape[0]
    if cells > min(DENSE_CELLS, DENSE_PER_VOXEL * visits):
        return None
    stride = np.array([math.prod(sizes[:a]) for a in range(dim)], dtype=np.int64)
    move = np.where(du < 0, -stride, stride)
    near = _near_ends(beams, config)
    enter = np.full(key0.shape[0], np.inf) if near is None else _enter_near(near, start_pt, end_pt)
    state = ray_kernel.state_map(cells)
    start = (key0 - low) @ stride
    box = chord_box(config)
    weights = np.zeros(state.size if box else 0, dtype=np.int32)
    walk_chord = (key0, box, weights) if box else None
    ray_kernel.walk_segments(start, move, crossings, gap, np.abs(du), enter, state, walk_chord)
    hit_cell = (hit_keys - low) @ stride
    # the first return per voxel, in beam order, at the file's precision
    points = step_points(return_steps(returns, hit_keys, res, depth), hit_keys, res, depth)
    marks = ray_kernel.read_marks(
        state, low, extent, hit_cell, points, visits, weights if box else None
    )
    n, k = marks.hits.size, config.clear_scans
    chord = strong_chord = tail_chord = None
    if box:
        chord, strong_chord, tail_chord = _one_look_sums(marks.shares, marks.strong_shares, config)
    # a voxel with a return has no free look to summarise, one without has its strong
    # look (if any) as its head and its tail; without forgetting no look is weak
    return VoxelObservations(
        marks.keys,
        marks.hits,
        marks.frees,
        marks.weak,
        marks.first_hit,
        k,
        marks.strong,
        marks.strong,
        np.zeros(n, dtype=np.int64),
        np.full((n, dim), np.nan),
        chord,
        strong_chord,
        tail_chord,
    )


def one_scan_summary(obs: VoxelObservations, clear_scans: int) -> VoxelObservations:
    """The newer-evidence summary of one scan's observations (:func:`_summarise`'s, directly).

    In one scan a voxel is seen occupied or free, never both: one with a return has no
    free look before or after it and nothing to restart; one without has its strong
    free look (if any) as both its head and its tail.
    """
    held = obs.hits > 0
    free_run = np.where(held, 0, obs.strong_frees)
    return dataclasses.replace(
        obs,
        clear_scans=clear_scans,
        head_frees=free_run,
        tail_frees=free_run.copy(),
        restart_hits=np.zeros(obs.hits.size, dtype=np.int64),
        restart_hit=np.full(obs.first_hit.shape, np.nan),
    )


def _combine(
    hit_vox: IntArray,
    hit_n: IntArray,
    free_vox: IntArray,
    free_n: IntArray,
    hit_points: np.ndarray,
    dim: int,
) -> VoxelObservations:
    """Static observations from sorted unique packed voxels, counts and first returns."""
    if merge_kernel.AVAILABLE:
        packed, at, at_free = merge_kernel.merge_positions(hit_vox, free_vox)
    else:
        packed = merge_unique(hit_vox, free_vox)
        at, at_free = np.searchsorted(packed, hit_vox), np.searchsorted(packed, free_vox)
    hits = np.zeros(packed.size, dtype=np.int64)
    frees = np.zeros(packed.size, dtype=np.int64)
    first_hit = np.full((packed.size, dim), np.nan)
    hits[at] = hit_n
    first_hit[at] = hit_points
    frees[at_free] = free_n
    return _without_forgetting(unpack_keys(packed, dim), hits, frees, first_hit)


def _without_forgetting(
    keys: IntArray, hits: IntArray, frees: IntArray, first_hit: np.ndarray
) -> VoxelObservations:
    """Observations without a newer-evidence summary (``clear_scans`` 0)."""
    zeros = np.zeros(hits.size, dtype=np.int64)
    none = np.full(first_hit.shape, np.nan)
    return VoxelObservations(keys, hits, frees, zeros, first_hit, 0, frees, frees, zeros, none)


def _summarise(
    obs: VoxelObservations,
    hit_codes: IntArray,
    hit_points: np.ndarray,
    free_codes: IntArray,
    clear_scans: int,
) -> VoxelObservations:
    """Add the newer-evidence summary of K = ``clear_scans`` from the (scan, voxel) codes.

    ``hit_codes`` (ascending) and ``hit_points`` are each (scan, voxel)'s code and first
    return; ``free_codes`` the (scan, voxel) codes seen free. Every voxel has at most
    one event per scan, so its events sorted by scan are its sequence of scans.
    """
    dim = obs.keys.shape[1]
    bits = KEY_BITS * dim
    mask = (1 << bits) - 1
    codes = np.concatenate([hit_codes, free_codes])
    # events ordered by voxel, then scan (the scan number fits below the voxel's bits)
    order = np.argsort(((codes & mask) << 12) | (codes >> bits))
    voxel = (codes & mask)[order]
    is_hit = order < hit_codes.size
    n = voxel.size
    new_group = np.r_[True, voxel[1:] != voxel[:-1]] if n else np.zeros(0, dtype=bool)
    starts = np.flatnonzero(new_group)
    run = np.cumsum(new_group) - 1  # the voxel's run of events
    rank = np.arange(n) - starts[run]
    # index into obs (voxels ascending; a voxel seen only weakly free has no events)
    group = np.searchsorted(pack_keys(obs.keys), voxel)
    size = np.zeros(obs.hits.size, dtype=np.int64)
    size[group[starts]] = np.diff(np.r_[starts, n])
    hits_at = np.flatnonzero(is_hit)
    hit_group, hit_rank = group[hits_at], rank[hits_at]
    last_of_group = np.r_[hit_group[1:] != hit_group[:-1], True] if hits_at.size else hits_at > 0
    first_of_group = np.r_[True, hit_group[1:] != hit_group[:-1]] if hits_at.size else hits_at > 0
    head = obs.strong_frees.copy()
    tail = obs.strong_frees.copy()
    head[hit_group[first_of_group]] = hit_rank[first_of_group]
    tail[hit_group[last_of_group]] = size[hit_group[last_of_group]] - 1 - hit_rank[last_of_group]
    # a run of >= K frees between two returns of a voxel: the later return restarts it
    same = hit_group[1:] == hit_group[:-1]
    long_gap = same & (hit_rank[1:] - hit_rank[:-1] - 1 >= clear_scans)
    after = np.flatnonzero(long_gap) + 1  # positions in the hit events list
    last = np.r_[hit_group[after][1:] != hit_group[after][:-1], True] if after.size else after > 0
    after = after[last]
    restart_hits = np.zeros(obs.hits.size, dtype=np.int64)
    restart_hit = np.full(obs.first_hit.shape, np.nan)
    g = hit_group[after]
    group_end = np.searchsorted(hit_group, g, side="right")
    restart_hits[g] = group_end - after
    restart_hit[g] = hit_points[order[hits_at[after]]]
    return VoxelObservations(
        obs.keys,
        obs.hits,
        obs.frees,
        obs.weak_frees,
        obs.first_hit,
        clear_scans,
        head,
        tail,
        restart_hits,
        restart_hit,
        obs.chord,
        obs.strong_chord,
        obs.tail_chord,
    )


def merge_observations(parts: list[VoxelObservations], dim: int) -> VoxelObservations:
    """The observations of consecutive runs of scans, given in time order.

    Counts add per voxel; the first part with a return in a voxel gives its first
    return; the newer-evidence summaries compose (the parts share ``clear_scans``).
    """
    if not parts:
        empty = np.zeros(0, dtype=np.int64)
        return _without_forgetting(
            np.zeros((0, dim), dtype=np.int64), empty, empty, np.zeros((0, dim))
        )
    out = parts[0]
    for part in parts[1:]:  # one iteration per part
        out = _one_run_then_another(out, part, dim)
    return out


def _on_voxels(obs: VoxelObservations, packed: IntArray, union: IntArray) -> VoxelObservations:
    """``obs`` on the voxels ``union`` (a superset): absent voxels saw nothing."""
    at = np.searchsorted(union, packed)
    n, d = union.size, obs.first_hit.shape[1]

    def put(values: np.ndarray, fill: float) -> np.ndarray:
        full = np.full((n, *values.shape[1:]), fill, dtype=values.dtype)
        full[at] = values
        return full

    return VoxelObservations(
        unpack_keys(union, d),
        put(obs.hits, 0),
        put(obs.frees, 0),
        put(obs.weak_frees, 0),
        put(obs.first_hit, np.nan),
        obs.clear_scans,
        put(obs.head_frees, 0),
        put(obs.tail_frees, 0),
        put(obs.restart_hits, 0),
        put(obs.restart_hit, np.nan),
        None if obs.chord is None else put(obs.chord, 0),
        None if obs.strong_chord is None else put(obs.strong_chord, 0),
        None if obs.tail_chord is None else put(obs.tail_chord, 0),
    )


def _one_run_then_another(
    a: VoxelObservations, b: VoxelObservations, dim: int
) -> VoxelObservations:
    """The observations of run ``a`` followed by run ``b``."""
    if a.clear_scans != b.clear_scans:
        raise ValueError("observations of different clear_scans cannot be merged")
    pa, pb = pack_keys(a.keys), pack_keys(b.keys)
    union = sorted_unique(np.concatenate([pa, pb]).astype(np.int64))
    a, b = _on_voxels(a, pa, union), _on_voxels(b, pb, union)
    has_a, has_b = a.hits > 0, b.hits > 0
    first_hit = np.where(has_a[:, None], a.first_hit, b.first_hit)
    hits, frees = a.hits + b.hits, a.frees + b.frees
    k = a.clear_scans
    chord = strong_chord = tail_chord = None
    if a.chord is not None and b.chord is not None:
        assert a.strong_chord is not None
        assert a.tail_chord is not None
        assert b.strong_chord is not None
        assert b.tail_chord is not None
        chord = _then(a.chord, a.frees, b.chord)
        strong_chord = _then(a.strong_chord, a.strong_frees, b.strong_chord)
        rows = np.arange(a.hits.size)
        carried = a.tail_chord + _first_looks(b.strong_chord, rows, k - a.tail_frees)
        tail_chord = np.where(has_b, b.tail_chord, carried) if k else a.tail_chord
    if not k:
        out = _without_forgetting(a.keys, hits, frees, first_hit)
        return dataclasses.replace(
            out, chord=chord, strong_chord=strong_chord, tail_chord=tail_chord
        )
    head = np.where(has_a, a.head_frees, a.strong_frees + b.head_frees)
    tail = np.where(has_b, b.tail_frees, b.strong_frees + a.tail_frees)
    middle = has_a & has_b & (a.tail_frees + b.head_frees >= k)
    from_b = b.restart_hits > 0
    from_middle = ~from_b & middle
    from_a = ~from_b & ~middle & (a.restart_hits > 0)
    restart_hits = np.select(
        [from_b, from_middle, from_a], [b.restart_hits, b.hits, a.restart_hits + b.hits], 0
    )
    restart_hit = np.select(
        [from_b[:, None], from_middle[:, None], from_a[:, None]],
        [b.restart_hit, b.first_hit, a.restart_hit],
        np.nan,
    )
    weak = a.weak_frees + b.weak_frees
    return VoxelObservations(
        a.keys,
        hits,
        frees,
        weak,
        first_hit,
        k,
        head,
        tail,
        restart_hits,
        restart_hit,
        chord,
        strong_chord,
        tail_chord,
    )


def _first_looks(prefix: IntArray, rows: IntArray, m: IntArray) -> IntArray:
    """Rows of ``prefix`` (:class:`VoxelObservations`' ``chord``): their first ``m`` looks' sums.

    ``m`` is clipped to ``[0, c]``; 0 looks sum to 0.
    """
    c = prefix.shape[1]
    out: IntArray = np.where(m > 0, prefix[rows, np.clip(m - 1, 0, c - 1)], 0)
    return out


def _then(a: IntArray, a_looks: IntArray, b: IntArray) -> IntArray:
    """Prefix sums of run ``a``'s looks (``a_looks`` of them) followed by run ``b``'s."""
    c = a.shape[1]
    m = np.arange(1, c + 1)[None, :]
    rest = m - a_looks[:, None]  # of b's looks, how many fall in the first m
    rows = np.arange(a.shape[0])[:, None]
    from_b = np.where(rest > 0, b[rows, np.clip(rest - 1, 0, c - 1)], 0)
    out: IntArray = a + from_b
    return out


def newer_evidence_wins(
    hits: IntArray,
    frees: IntArray,
    seen_hit: NDArray[np.bool_],
    seen_free: NDArray[np.bool_],
    seen_weakly: NDArray[np.bool_],
    clear_scans: int,
    evidence_cap: int,
) -> tuple[IntArray, IntArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """One scan's observations applied to voxel states: the lattice engine's evidence rule.

    Parameters
    ----------
    hits, frees : ndarray of int, shape (p,)
        Each voxel's return count and free count before the scan.
    seen_hit : ndarray of bool, shape (p,)
        The scan has a return in the voxel.
    seen_free : ndarray of bool, shape (p,)
        The scan's free segments cross the voxel (and it holds none of its returns).
    seen_weakly : ndarray of bool, shape (p,)
        ... only within ``clear_margin`` of their returns or on no-return beams: free
        evidence that does not count towards forgetting a return.
    clear_scans, evidence_cap : int
        K (0: a static world) and the saturation of the return count.

    Returns
    -------
    hits, frees : ndarray of int, shape (p,)
        The counts after the scan.
    renewed : ndarray of bool, shape (p,)
        The voxel's kept return becomes this scan's first return in it.
    forgotten : ndarray of bool, shape (p,)
        The voxel's returns are forgotten.
    """
    h0, f0 = hits.astype(np.int64), frees.astype(np.int64)
    if not clear_scans:  # a static world: both counts add, the first return stays
        h = np.minimum(h0 + seen_hit, evidence_cap)
        f = np.minimum(f0 + seen_free, evidence_cap)
        return h, f, (h0 == 0) & seen_hit, np.zeros(h.size, dtype=bool)
    holding = h0 > 0
    # without a return every free look counts; holding one, only a strong look does
    counted = seen_free & (~holding | ~seen_weakly)
    f = np.where(seen_hit, 0, np.minimum(f0 + counted, clear_scans))  # a return restarts it
    forgotten = holding & ~seen_hit & (f >= clear_scans)
    h = np.where(seen_hit, np.minimum(h0 + 1, evidence_cap), np.where(forgotten, 0, h0))
    return h, f, seen_hit & ~holding, forgotten


@dataclass(frozen=True)
class VoxelState:
    """A voxel's evidence after a run of scans (:func:`advance`), per (voxel, copy) pair.

    Attributes
    ----------
    hits, frees : ndarray of int64, shape (p,)
        The new counts (saturated).
    position : ndarray of shape (p, d)
        The return to keep for the voxel where ``replace``; NaN elsewhere.
    replace : ndarray of bool, shape (p,)
        The voxel's kept return becomes ``position`` (a first or renewed return).
    drop : ndarray of bool, shape (p,)
        The voxel's kept return is forgotten (no return left).
    """

    hits: IntArray
    frees: IntArray
    position: np.ndarray
    replace: np.ndarray
    drop: np.ndarray


def advance(
    hits: IntArray,
    frees: IntArray,
    obs: VoxelObservations,
    at: IntArray,
    evidence_cap: int,
) -> VoxelState:
    """Apply a run of scans' observations to voxel states, as the scans one by one would.

    The scans one by one are :func:`newer_evidence_wins` scan after scan; this applies
    the run's summary in one pass.

    Parameters
    ----------
    hits, frees : ndarray of int, shape (p,)
        The current counts of ``p`` voxel copies (a voxel lies in up to ``2**d`` leaf
        halo boxes; every copy holds the same state).
    obs : VoxelObservations
        The run's observations.
    at : ndarray of int, shape (p,)
        Each copy's voxel in ``obs``.
    evidence_cap : int
        Counts saturate at this; with the newer-evidence rule the free count
        saturates at K instead (it counts towards forgetting).

    Returns
    -------
    VoxelState
    """
    h0, f0 = hits.astype(np.int64), frees.astype(np.int64)
    n_h, n_f = obs.hits[at], obs.frees[at]
    k = obs.clear_scans
    seen = n_h > 0
    if not k:  # static: counts add, the first return stays
        replace = (h0 == 0) & seen
        position = np.where(replace[:, None], obs.first_hit[at], np.nan)
        h = np.minimum(h0 + n_h, evidence_cap)
        f = np.minimum(f0 + n_f, evidence_cap)
        return VoxelState(h, f, position, replace, np.zeros(h.size, dtype=bool))
    restart = obs.restart_hits[at] > 0
    first_on = seen & ~restart & ((h0 == 0) | (f0 + obs.head_frees[at] >= k))
    h = np.select([restart, first_on, seen], [obs.restart_hits[at], n_h, h0 + n_h], h0)
    # while a voxel holds a return only strong frees count (towards forgetting it);
    # without one every free counts; the free count saturates at K
    on = seen | (h0 > 0)
    f = np.select([seen, h0 > 0], [obs.tail_frees[at], f0 + obs.strong_frees[at]], f0 + n_f)
    cleared = on & (f >= k)
    h = np.where(cleared, 0, np.minimum(h, evidence_cap))
    f = np.minimum(f, k)
    replace = (restart | first_on) & ~cleared
    position = np.select(
        [(restart & replace)[:, None], (first_on & replace)[:, None]],
        [obs.restart_hit[at], obs.first_hit[at]],
        np.nan,
    )
    drop = (h0 > 0) & ((h == 0) | replace)
    return VoxelState(h, f, position, replace, drop)


CHORD_CAP = (1 << 16) - 1
"""Most summed chord shares a leaf keeps per voxel (uint16, in ``ray_kernel.CHORD_UNITS``:
64 whole chords)."""


def advance_chord(
    weights: NDArray[np.integer],
    hits: NDArray[np.integer],
    frees: NDArray[np.integer],
    obs: VoxelObservations,
    at: IntArray,
) -> IntArray:
    """Apply a run of scans' chord shares to voxels' summed shares, as one by one.

    A voxel's summed shares are those of the free looks its free count counts
    (:func:`advance`), saturated at :data:`CHORD_CAP`: in a static world (``clear_scans``
    0) its first ``lattice.evidence_cap`` looks; with newer evidence winning, up to K
    looks since its last return (a return restarts the sum as it restarts the free
    count), every look counting while the voxel holds no return and only strong ones
    (those counting towards forgetting) while it holds one. A look the count no longer
    counts adds nothing, so a revisit that changes no count changes no sum. The run's
    prefix sums (``obs.chord``, ``obs.strong_chord``, ``obs.tail_chord``) give what its
    scans one by one would.

    Parameters
    ----------
    weights : ndarray of int, shape (p,)
        The current sums of ``p`` voxel copies.
    hits, frees : ndarray of int, shape (p,)
        The copies' counts before the run (those :func:`advance` is given).
    obs : VoxelObservations
        The run's observations, with chord shares.
    at : ndarray of int, shape (p,)
        Each copy's voxel in ``obs``.

    Returns
    -------
    ndarray of int64, shape (p,)
    """
    if obs.chord is None or obs.strong_chord is None or obs.tail_chord is None:
        raise ValueError("the observations hold no chord shares")
    c = obs.chord.shape[1]
    w0 = weights.astype(np.int64)
    left = c - frees.astype(np.int64)  # looks the free count still counts
    every = _first_looks(obs.chord, at, left)
    if not obs.clear_scans:
        w = w0 + every
    else:
        strong = _first_looks(obs.strong_chord, at, left)
        w = np.select([obs.hits[at] > 0, hits > 0], [obs.tail_chord[at], w0 + strong], w0 + every)
    out: IntArray = np.minimum(w, CHORD_CAP)
    return out


def free_inputs(
    frees: NDArray[np.integer],
    chord: NDArray[np.integer] | None,
    config: MapConfig,
) -> tuple[np.ndarray, float]:
    """The free evidence a leaf GP sees, and its weight per unit.

    Parameters
    ----------
    frees : ndarray of int
        Effective free counts (:func:`effective_counts`).
    chord : ndarray of int, same shape, or None
        Summed chord shares (:func:`advance_chord`); used where
        ``lattice.free_evidence`` is ``"chord"`` (``None`` there: none kept, zeros).
    config : MapConfig

    Returns
    -------
    frees : ndarray
        ``frees`` itself (looks), or the summed shares where ``frees`` is positive.
    weight : float
        ``lattice.free_weight``, or ``lattice.chord_weight / CHORD_UNITS``.
    """
    lc = config.lattice
    if config.free_evidence != "chord":
        return frees, lc.free_weight
    if chord is None:
        return np.zeros(frees.shape, dtype=np.int64), 1.0
    return np.where(frees > 0, chord, 0), lc.chord_weight / ray_kernel.CHORD_UNITS


def effective_counts(
    hits: NDArray[np.integer], frees: NDArray[np.integer], evidence_cap: int, clear_scans: int
) -> tuple[NDArray[np.integer], NDArray[np.integer]]:
    """The counts a leaf GP sees: returns and free looks, saturated.

    Returns count up to ``evidence_cap``; free looks up to ``evidence_cap`` in a static
    world and up to ``clear_scans`` with newer evidence winning.

    With newer evidence winning (``clear_scans`` = K > 0) a voxel holding a return is
    occupied only: its later frees count only towards forgetting the return, so a wall
    voxel that grazing beams see free now and then does not flip its leaf. A voxel
    without one counts each scan that saw it free, up to K (the count the rule keeps
    anyway), each weighing ``lattice.free_weight``: a voxel seen free once, beside a wall,
    weighs little against the wall's returns, one seen free scan after scan (an opened
    doorway) K times as much.

    Parameters
    ----------
    hits, frees : ndarray of int, same shape
        Stored counts.
    evidence_cap, clear_scans : int

    Returns
    -------
    hits, frees : ndarray of int
    """
    h = np.minimum(hits, evidence_cap)
    f = np.minimum(frees, max(evidence_cap, clear_scans))
    if clear_scans:
        f *= h == 0  # f is a fresh array
    return h, f
