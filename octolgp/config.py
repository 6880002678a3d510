"""Frozen, validated configuration: one section per pipeline stage.

Every section is a frozen, slotted dataclass validated in ``__post_init__``; a bad
value raises :class:`~octolgp.errors.OctolgpError` naming the field. There are no
globals: two maps with different configs can live in one process.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from octolgp.errors import MapFileNotFound, OctolgpError

MAX_RESOLUTION = 1000.0
"""Largest voxel edge, metres: a kilometre voxel already spans the globe at tree depth 16,
and larger ones overflow the derived integer sizes."""


MAX_MEMORY_BUDGET_MB = 1e12
"""Largest ``memory_budget_mb``: the budget in bytes must fit a 64-bit integer."""

MIN_SPACING = 1e-6
"""Smallest node or lattice spacing, as a fraction of the length scale, and smallest
coarse box, metres: finer ones make node counts that overflow an integer."""

LENGTH_SCALE_RANGE = (1e-6, 1e6)
"""The length scales a map accepts, metres (learning keeps to [0.01, 100])."""

MAX_VARIANCE = 1e12
"""Largest signal or noise variance: ``α² σ²`` in PLSC must stay finite."""

MAX_PLSC = 1e6
"""Largest ``|α|`` and ``|β|`` of PLSC (learning keeps to [0.001, 1000] and [-100, 100])."""


def _positive(
    owner: str,
    name: str,
    value: object,
    *,
    allow_zero: bool = False,
    low: float | None = None,
    high: float | None = None,
    unit: str = "",
) -> None:
    """Raise unless ``value`` is a finite real number > 0 (or >= 0), in [low, high] if given."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = value >= 0 if allow_zero else value > 0  # type: ignore[operator]
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise OctolgpError(f"{owner}.{name} must be a finite number {bound}, got {value!r}")
    if low is not None and value < low:  # type: ignore[operator]
        raise OctolgpError(f"{owner}.{name} must be at least {low:g}{unit}, got {value!r}")
    if high is not None and value > high:  # type: ignore[operator]
        raise OctolgpError(f"{owner}.{name} must be at most {high:g}{unit}, got {value!r}")


def _integer(owner: str, name: str, value: object, lo: int, hi: int | None = None) -> None:
    """Raise unless ``value`` is an int in ``[lo, hi]``."""
    if not isinstance(value, int) or isinstance(value, bool) or value < lo:
        raise OctolgpError(f"{owner}.{name} must be an integer >= {lo}, got {value!r}")
    if hi is not None and value > hi:
        raise OctolgpError(f"{owner}.{name} must be an integer <= {hi}, got {value!r}")


def _fraction(owner: str, name: str, value: object, *, open_low: bool = False) -> None:
    """Raise unless ``value`` is a finite number in [0, 1] (or (0, 1))."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (0 < value < 1) if open_low else (0 <= value <= 1)  # type: ignore[operator]
    if not ok:
        rng = "(0, 1)" if open_low else "[0, 1]"
        raise OctolgpError(f"{owner}.{name} must be a number in {rng}, got {value!r}")


@dataclass(frozen=True, slots=True)
class Hyperparameters:
    """Kernel and PLSC hyperparameters.

    Parameters
    ----------
    length_scale : float
        Matérn ν=3/2 length scale ``l``, metres, in [1e-6, 1e6]
        (:data:`LENGTH_SCALE_RANGE`).
    signal_variance : float
        Signal variance ``σf²`` (the paper reports ``σf``, its square root), in
        (0, 1e12] (:data:`MAX_VARIANCE`).
    noise_variance : float
        Observation noise variance ``σn²`` (the paper reports ``σn``), in (0, 1e12].
    alpha, beta : float
        PLSC scale and offset: ``p(occupied) = Φ((α μ + β) / sqrt(1 + α² σ²))``, each in
        [-1e6, 1e6] (:data:`MAX_PLSC`), so that ``α² σ²`` stays finite.
    """

    length_scale: float = 1.0
    signal_variance: float = 1.0
    noise_variance: float = 0.1
    alpha: float = 1.0
    beta: float = 0.0

    def __post_init__(self) -> None:
        low, high = LENGTH_SCALE_RANGE
        _positive(
            "Hyperparameters", "length_scale", self.length_scale, low=low, high=high, unit=" m"
        )
        for name in ("signal_variance", "noise_variance"):
            _positive("Hyperparameters", name, getattr(self, name), high=MAX_VARIANCE)
        for name in ("alpha", "beta"):
            value = getattr(self, name)
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or not math.isfinite(value):
                raise OctolgpError(f"Hyperparameters.{name} must be a finite number, got {value!r}")
            if abs(value) > MAX_PLSC:
                raise OctolgpError(
                    f"Hyperparameters.{name} must be in [-{MAX_PLSC:g}, {MAX_PLSC:g}], got {value!r}"
                )


@dataclass(frozen=True, slots=True)
class TrainingConfig:
    """How beams become training data (scan → hits and free segments).

    Parameters
    ----------
    free_margin : float or None
        A free segment stops this many metres short of its hit so that it does not
        cancel the hit. ``None`` means one map resolution.
    free_range : float or None
        Metres from the sensor that a beam's evidence reaches, as OctoMap's
        ``maxrange``: a no-return beam is free up to it, and a return farther away
        becomes a free segment up to it without its hit. ``math.inf`` (default):
        every beam whole.
    no_return_range : float or None
        Metres a no-return beam (one reaching the scan's ``max_range``) is free up to,
        at most ``free_range``: it says only that nothing returned, which glass, dark
        surfaces and open doors do too, and its free segment to ``max_range`` spreads
        free space far beyond anything seen (80 m rays on an indoor log). ``math.inf``:
        to ``max_range``. ``None``: the default for the map's dimension
        (:data:`DEFAULT_NO_RETURN_RANGE`).
    dedup : bool
        Keep one hit per voxel and one free segment per voxel of its end point.
        Without it, free evidence swamps the hits on real logs.
    quadrature_spacing : float
        Clenshaw-Curtis node spacing along a segment, as a fraction of the
        length scale, at least 1e-6 (:data:`MIN_SPACING`). A segment of length ``L``
        gets ``ceil(L / (spacing * length_scale)) + 1`` nodes (clamped below).
    min_quadrature_nodes, max_quadrature_nodes : int
        Bounds on the nodes per segment.
    """

    free_margin: float | None = None
    dedup: bool = True
    quadrature_spacing: float = 0.5
    min_quadrature_nodes: int = 3
    max_quadrature_nodes: int = 33
    free_range: float = math.inf
    no_return_range: float | None = None

    def __post_init__(self) -> None:
        if self.free_margin is not None:
            _positive("TrainingConfig", "free_margin", self.free_margin, allow_zero=True)
        for name in ("free_range", "no_return_range"):
            r = getattr(self, name)
            ok = isinstance(r, int | float) and not isinstance(r, bool)
            if (r is not None or name == "free_range") and (not ok or math.isnan(r) or r <= 0):
                raise OctolgpError(
                    f"TrainingConfig.{name} must be math.inf or a number of metres > 0, got {r!r}"
                )
        if not isinstance(self.dedup, bool):
            raise OctolgpError(f"TrainingConfig.dedup must be a bool, got {self.dedup!r}")
        _positive("TrainingConfig", "quadrature_spacing", self.quadrature_spacing, low=MIN_SPACING)
        _integer("TrainingConfig", "min_quadrature_nodes", self.min_quadrature_nodes, 2)
        _integer(
            "TrainingConfig",
            "max_quadrature_nodes",
            self.max_quadrature_nodes,
            self.min_quadrature_nodes,
        )


@dataclass(frozen=True, slots=True)
class PartitionConfig:
    """Coarse boxes, iterative k-means under a size cap, and overlap (Kim & Kim §III-B).

    Parameters
    ----------
    box_size : float
        Edge of the coarse boxes the hits are first split into, metres, at least 1e-6
        (:data:`MIN_SPACING`).
    max_cluster_size : int
        Cap on a cluster's own training items (hits plus their free segments)
        before extension; k-means is repeated on any cluster over it.
    overlap : float
        Extension of each cluster: its box grows by this fraction of its extent on
        every side, and it takes in every hit (with its segment) inside; at most 100, so
        that the grown boxes stay finite. Default 0.2.
    seed : int
        Seed of k-means.
    """

    box_size: float = 10.0
    max_cluster_size: int = 200
    overlap: float = 0.2
    seed: int = 0

    def __post_init__(self) -> None:
        _positive("PartitionConfig", "box_size", self.box_size, low=MIN_SPACING, unit=" m")
        _integer("PartitionConfig", "max_cluster_size", self.max_cluster_size, 2)
        _positive("PartitionConfig", "overlap", self.overlap, allow_zero=True, high=100.0)
        _integer("PartitionConfig", "seed", self.seed, 0)


@dataclass(frozen=True, slots=True)
class LearningConfig:
    """Which data the hyperparameters are learnt on.

    Length scales learnt on one small subset swing widely, so the log marginal
    likelihood is summed over several clusters that share the hyperparameters.

    Parameters
    ----------
    max_clusters : int
        Number of clusters (spread over the map) whose likelihoods are summed.
    max_items_per_cluster : int
        Each chosen cluster is randomly subsampled to at most this many items.
    seed : int
        Seed for the choice of clusters and items.
    objective : {"lml", "lml+loo"}
        ``"lml"`` (default): the kernel by log marginal likelihood, then α, β by the
        LOO predictive probability (R&W §6.5). ``"lml+loo"`` then refines all five
        jointly by the LOO predictive probability, starting from that point; opt-in,
        as on a noise-free scene it drives the signal variance to its bound
        (``BENCHMARKS.md``, "Kim & Kim Table II").
    model : {"engine", "voxels", "segments"}
        The observations learnt on (:mod:`octolgp.gp.learning`). ``"voxels"``: each
        observed voxel a point, the lattice engine's model. ``"segments"``: hits and
        free segments with integral kernels on the partition's clusters, the exact
        engine's and the batch map's model. ``"engine"`` (default): the online
        engine's own, voxels for ``online.engine="lattice"``, segments for
        ``"exact"``.
    max_beams : int or None
        On the voxel model, the learning scans are thinned to every k-th beam (the
        smallest k) so that at most this many beams are turned into voxel
        observations; ``None``: every beam. The sets hold a few thousand items and
        only the voxels near their seeds are counted, but every beam is walked: five
        lidar scans to 80 m cross millions of voxels. 40 scans of a 2D laser (up to
        361 beams) stay whole, five filtered lidar scans keep every 2nd to 4th beam.
        Default 25_000.
    """

    max_clusters: int = 8
    max_items_per_cluster: int = 300
    seed: int = 0
    objective: str = "lml"
    model: str = "engine"
    max_beams: int | None = 25_000

    def __post_init__(self) -> None:
        if self.objective not in ("lml+loo", "lml"):
            raise OctolgpError(
                f"LearningConfig.objective must be 'lml+loo' or 'lml', got {self.objective!r}"
            )
        if self.model not in ("engine", "voxels", "segments"):
            raise OctolgpError(
                f"LearningConfig.model must be 'engine', 'voxels' or 'segments', got {self.model!r}"
            )
        _integer("LearningConfig", "max_clusters", self.max_clusters, 1)
        _integer("LearningConfig", "max_items_per_cluster", self.max_items_per_cluster, 4)
        _integer("LearningConfig", "seed", self.seed, 0)
        if self.max_beams is not None:
            _integer("LearningConfig", "max_beams", self.max_beams, 1)


@dataclass(frozen=True, slots=True)
class OgmConfig:
    """The log-odds occupancy grid baseline; OctoMap's default sensor model.

    Parameters
    ----------
    prob_hit, prob_miss : float
        Inverse sensor model for the end voxel and the traversed voxels.
    clamping_thres_min, clamping_thres_max : float
        Probability clamping bounds.
    """

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamping_thres_min: float = 0.1192
    clamping_thres_max: float = 0.971

    def __post_init__(self) -> None:
        for name in ("prob_hit", "prob_miss", "clamping_thres_min", "clamping_thres_max"):
            _fraction("OgmConfig", name, getattr(self, name), open_low=True)
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise OctolgpError("OgmConfig.prob_hit must be > 0.5 > OgmConfig.prob_miss")
        if not self.clamping_thres_min < self.clamping_thres_max:
            raise OctolgpError(
                "OgmConfig.clamping_thres_min must be below OgmConfig.clamping_thres_max"
            )


@dataclass(frozen=True, slots=True)
class OnlineConfig:
    """The online mapper: which leaf engine, the leaf grid, learning, threads, forgetting.

    Parameters
    ----------
    engine : {"lattice", "exact"}
        The leaf engine. ``"lattice"`` (default): each leaf keeps per-voxel observation
        counts of its halo box and is a sparse GP on an inducing lattice whose kernel
        tables every leaf shares (:mod:`octolgp.engines.lattice`, tuned by
        :class:`LatticeConfig`). ``"exact"``: the paper's local GP on hits and free
        segments with integral kernels (:mod:`octolgp.engines.exact`, tuned by
        :class:`ExactConfig`), the reference the lattice engine is tested against and
        much slower in 3D (``BENCHMARKS.md``, "Lattice engine").
    leaf_depth : int or None
        OctoMap tree depth of the leaves; a leaf spans ``2**(tree_depth - leaf_depth)``
        voxels per axis. ``None`` (default): 16 × 16 voxels in 2D, 16³ in 3D with the
        lattice engine and 8³ with the exact one (the lattice engine fits a leaf in tiles
        of 4 voxels a side, whose GP is cheaper per voxel: ``LatticeConfig.tile_voxels``;
        its leaf is the unit of per-scan bookkeeping, so a large leaf makes a scan's
        insert cheaper for the same values).
    halo : float or None
        Overlap margin around each leaf as a fraction of its edge, in ``[0, 0.5)`` (of
        its tiles' edge where the lattice engine fits a leaf in smaller tiles, rounded
        up to whole voxels). ``None`` (default): 0.45 for the 2D lattice engine (2 voxels
        around its tiles of 4, about half a length scale of the indoor logs at 0.1 m:
        with 1 voxel, walls' insides and unseen corners read less occupied), 0.2
        otherwise (1 voxel around a 3D tile of 4).
    learn_scans : int or None
        With ``MapConfig.hyperparameters=None`` the first this many scans are buffered,
        the hyperparameters are learnt on them and then held fixed. ``None`` (default):
        40 in 2D (the robot has left its first room by then) and 5 in 3D, where one
        lidar scan holds a hundred times the beams of a 2D scan.
    n_jobs : int or None
        Threads refitting leaves in parallel (BLAS held to one thread each). ``None``
        (default): the CPU cores the process may use, at most 8. A runtime setting, not
        part of the map: the exact engine's results do not depend on it, the lattice
        engine's only to rounding (:mod:`octolgp.gp.lattice`).
    clear_scans : int or None
        How fast the map forgets (newer evidence wins, :func:`octolgp.observations.
        newer_evidence_wins`): a voxel's returns are forgotten once this many scans have
        seen it free since its last return, and a return clears the voxel's free count,
        so a moved object's voxels read free after the robot has looked through them this
        many times. ``0``: a static world, every observation kept for good. ``None``
        (default): 5 with the lattice engine, 0 with the exact one (which keeps the first
        evidence per voxel and cannot forget). In 0..255 (``BENCHMARKS.md``, "A changing
        world").
    max_scan_points : int
        ``insert_scan`` refuses a scan with more points than this (an
        :class:`~octolgp.errors.OctolgpError` naming this field), so that one huge scan
        cannot exhaust memory. Downsample such a scan (:meth:`Scan.downsample`) or raise
        the limit. Default 1_000_000.
    prune : bool or None
        Collapse a leaf whose voxels are all confidently free or all confidently
        occupied to one value, its least confident (OctoMap-style pruning at its clamping
        bounds): less memory, but every voxel of the leaf then reads that value, which
        flattens the ranking of confident voxels. ``None`` (default): on, except for the
        3D lattice engine, whose large leaves would lose too much (with leaves of 8³,
        held-out AUC of the KITTI fixture 0.981 → 0.919, the sparse street 0.985 → 0.962;
        BENCHMARKS.md, "Live 3D, second part") for about 40 % more leaf memory.
    defer_fit : bool
        Fit the leaves a scan changes when the map is next read (a query, an export, a
        save, :meth:`OnlineMap.settle <octolgp.OnlineMap.settle>`) rather than in
        ``insert_scan``: a sensor that keeps touching a leaf scan after scan costs one
        fit of it per read, not one per scan, and an insert is the observation and the
        evidence update only. What a read returns is the same either way. It applies
        to the lattice engine on a map without a sink (a sink shows every step's
        values); a map with a file or a memory budget defers once it has its
        hyperparameters (the file keeps a lattice leaf's evidence, not its values).
        Otherwise leaves are fitted in ``insert_scan``. Default True.
    scan_precision : float or None
        Metres to which a scan's beams are rounded as it is inserted: each beam's
        offset from the sensor becomes a whole number of steps (a beam that rounding
        would carry across ``max_range`` goes a step further along itself, so it keeps
        its kind), and the beams are sorted by their steps. It is part of the map's
        definition: the map is built from the rounded scans, and the map file's
        journal stores them compactly and exactly (zlib of the sorted steps'
        differences, about 2 bytes a point of a filtered lidar scan at 0.01 m, against
        24), so a pose correction replays what the map was built from. ``None``: scans
        are kept as given (float64; files written before
        this setting). Default 0.01.
    journal_scans : int or None
        How many of the latest scans a map file's journal keeps for pose corrections
        (:meth:`OnlineMap.correct_scans <octolgp.OnlineMap.correct_scans>`). Every this
        many scans the map file marks a checkpoint and keeps, for each leaf changed
        since, its evidence as of the checkpoint; scans before the oldest checkpoint a
        correction may need are dropped from the journal (their evidence stays in the
        leaves and the checkpoint), so the journal holds between this many and twice
        this many scans and a correction reaches at least the latest this many (100 s
        of a 10 Hz lidar at the default). A correction of an older scan is refused.
        ``None``: every scan is kept (files written before this setting). Default 1000.
    """

    engine: str = "lattice"
    leaf_depth: int | None = None
    halo: float | None = None
    learn_scans: int | None = None
    n_jobs: int | None = None
    clear_scans: int | None = None
    max_scan_points: int = 1_000_000
    prune: bool | None = None
    defer_fit: bool = True
    scan_precision: float | None = 0.01
    journal_scans: int | None = 1000

    def __post_init__(self) -> None:
        if self.engine not in ("lattice", "exact"):
            raise OctolgpError(
                f"OnlineConfig.engine must be 'lattice' or 'exact', got {self.engine!r}"
            )
        if self.leaf_depth is not None:
            _integer("OnlineConfig", "leaf_depth", self.leaf_depth, 1, 16)
        ok = isinstance(self.halo, int | float) and not isinstance(self.halo, bool)
        if self.halo is not None and (
            not ok or not math.isfinite(self.halo) or not 0 <= self.halo < 0.5
        ):
            raise OctolgpError(f"OnlineConfig.halo must be a number in [0, 0.5), got {self.halo!r}")
        if self.learn_scans is not None:
            _integer("OnlineConfig", "learn_scans", self.learn_scans, 1)
        if self.n_jobs is not None:
            _integer("OnlineConfig", "n_jobs", self.n_jobs, 1)
        if self.clear_scans is not None:
            _integer("OnlineConfig", "clear_scans", self.clear_scans, 0, 255)
            if self.clear_scans and self.engine != "lattice":
                raise OctolgpError(
                    "OnlineConfig.clear_scans must be 0 or None with engine='exact' "
                    f"(forgetting needs the lattice engine), got {self.clear_scans}"
                )
        _integer("OnlineConfig", "max_scan_points", self.max_scan_points, 1)
        if self.prune is not None and not isinstance(self.prune, bool):
            raise OctolgpError(f"OnlineConfig.prune must be a bool, got {self.prune!r}")
        if not isinstance(self.defer_fit, bool):
            raise OctolgpError(f"OnlineConfig.defer_fit must be a bool, got {self.defer_fit!r}")
        if self.journal_scans is not None:
            _integer("OnlineConfig", "journal_scans", self.journal_scans, 1)
        p = self.scan_precision
        ok = isinstance(p, int | float) and not isinstance(p, bool)
        if p is not None and (not ok or not math.isfinite(p) or not 1e-6 <= p <= 1.0):
            raise OctolgpError(
                f"OnlineConfig.scan_precision must be None or a number of metres in [1e-6, 1], "
                f"got {p!r}"
            )


FREE_EVIDENCE = ("looks", "chord")
"""The weightings of a lattice leaf's free voxels (``LatticeConfig.free_evidence``)."""


@dataclass(frozen=True, slots=True)
class LatticeConfig:
    """The lattice leaf engine's advanced settings (:mod:`octolgp.engines.lattice`).

    Parameters
    ----------
    evidence_cap : int
        Scans counted per voxel and class (occupied, free). ``1`` keeps whether a voxel
        was ever seen occupied and, in a static map, ever seen free, so a static revisit
        changes nothing and costs nothing; with forgetting on, free looks count up to
        ``OnlineConfig.clear_scans`` instead. Default 1.
    free_weight : float
        A free observation counts this much of a return (its noise variance is
        ``σn² / free_weight``), so that free space, which a scan observes in far more
        voxels than it hits, does not swamp the returns. With forgetting on, a voxel's
        free looks count up to ``clear_scans`` scans
        (:func:`~octolgp.observations.effective_counts`): a voxel seen free once, beside
        a wall, weighs little, one seen free scan after scan (an opened doorway) the
        most. In [1e-6, 1e6], so that ``σn² / free_weight`` stays finite. Default 0.05:
        with free evidence in every voxel a free segment passes through, it gives a
        held-out AUC at or above 0.06's on the room, both streets, the sparse street and
        3DTK (``tools/bench_3d.py``; the KITTI fixture 2e-4 below) and on Intel and FR079
        (``tools/quality_variants.py``); weights above 0.06 lose on every scene. Lower
        weights gain more AUC but leave a cell at an opened door's frame reading
        occupied (0.045 already). With ``free_evidence = "chord"`` (the 3D default) the
        leaves weigh ``chord_weight`` instead, and ``free_weight`` weighs free looks in
        hyperparameter learning only.
    free_evidence : {"looks", "chord"} or None
        How much a free voxel weighs in its leaf's GP. ``"looks"``: each
        counted free look weighs ``free_weight``
        (:func:`~octolgp.observations.effective_counts`). ``"chord"``: each scan's free
        segment gives every voxel it passes through the voxel's share of the segment's
        chord through the key-aligned box of 16 voxels a side holding the voxel
        (:data:`~octolgp.observations.CHORD_BOX`; the part of the chord inside the voxel
        over the chord's length in the box), the leaf keeps per voxel the sum of those
        shares over the free looks its free count counts (up to ``clear_scans`` since the
        voxel's last return; ``evidence_cap`` in a static world), and a free voxel weighs
        ``chord_weight`` times it: a long chord through empty space is spread thin over its
        voxels, a short one ending before a return is concentrated on few, as a free piece
        of the exact engine is one observation per leaf box. ``None`` (default):
        :data:`DEFAULT_FREE_EVIDENCE` (files written before this setting: ``"looks"``).
    chord_weight : float
        With ``free_evidence = "chord"``, the weight of a whole chord through a box (a
        free voxel weighs this times its summed shares). In [1e-6, 1e6]. Default 0.03.
    inducing_spacing : float or None
        Largest spacing of the inducing lattice as a fraction of the length scale, at
        least 1e-6 (:data:`MIN_SPACING`); the lattice gets
        ``ceil(halo box edge / (spacing × l))`` points per axis, at least
        ``min_inducing_per_axis`` and at most ``max_inducing_per_axis``. ``None`` (default): 0.4 in 2D, 0.5 in 3D,
        where a denser lattice does not help and a tile costs ``k**(3 d)``.
    max_inducing_per_axis : int or None
        Cap on the lattice points per axis (the product table holds
        ``H k**d (k**d + 1) / 2`` floats). ``None`` (default): 12 in 2D, 4 in 3D.
    clear_margin : float or None
        With forgetting on: metres before a return within which its beam's free segment
        does not count towards forgetting (it is still free evidence), as a beam grazing
        a wall crosses wall voxels just before its return. No-return beams never count
        towards forgetting either (a dark or glass surface returns nothing). ``None``
        (default): 5 voxels.
    tile_voxels : int or None
        Edge, in voxels, of the tiles a leaf's GP is fitted in: each tile is a local GP of
        its own on its halo box (``OnlineConfig.halo`` of the tile's edge, rounded up to
        whole voxels) with its own inducing lattice, and the leaf stores the tiles' halo
        boxes together. A tile costs ``k**6`` in its lattice, so small tiles are cheap per
        voxel, while a leaf costs Python bookkeeping per step, so large leaves are cheap
        per voxel: the map's values are those of leaves the size of a tile, with fewer
        leaves to keep, and a step refits only the tiles whose halo boxes saw a change. A
        power of two up to the leaf's edge. ``None`` (default): 4 (16 tiles a 2D leaf of
        16 × 16, 64 a 3D leaf of 16³).
    min_inducing_per_axis : int or None
        Fewest lattice points per axis whatever the length scale (a long length scale
        does not make the posterior smooth where the noise is small: a coarse lattice
        blurs a return over several voxels), at most ``max_inducing_per_axis``. ``None``
        (default): points at most 4/3 voxels apart in 2D (6 on the default tile's halo
        box of 8: with 4, a wall's occupancy spread a cell into a doorway beside it; with
        5, a moved crate's last cell cleared a look late), 2 voxels in 3D (3 on the tile's
        halo box of 6: with 2, which a learnt length scale of metres gave, the P = 0.5
        level set lay about a voxel in front of surfaces; 4 costs 3.5 times as much a fit).
    fill_voxels : int or None
        How far the GP may fill space no beam saw: a voxel takes the GP's value only
        when some voxel within this many voxels of it (along every axis: a cube of edge
        ``2 k + 1``) was observed, free or occupied; farther out it holds no value and
        reads unknown (0.5), like space outside every leaf. The gaps between rays
        within ``k`` voxels of them are filled, rooms no beam entered and space beyond
        the last observation are not. Both leaf engines keep it (the exact engine in a
        seen mask per leaf, :mod:`octolgp.engines.known`). At most the halo in voxels of
        what the engine fits: a tile's (the exact engine: a leaf's). ``-1``: every voxel
        of a leaf takes the GP's value (files written before this setting).
        ``None`` (default): :data:`DEFAULT_FILL_VOXELS`.
    sweep_angle : float or None
        The field of view between beams counts as seen (2D scans): two beams of a scan
        adjacent in direction and at most this many degrees apart sweep the sector
        between them, up to the nearer of their free segments' ends (the return less
        ``free_margin``, or the no-return range), and every voxel whose centre lies in
        that sector counts as observed for ``fill_voxels`` (it is known), without being
        evidence for the GP. Space beyond every beam's free segment and rooms no beam
        entered stay unknown. ``0`` turns the rule off (files written before this
        setting); 3D scans take ``0`` only. ``None`` (default):
        :data:`DEFAULT_SWEEP_ANGLE`.
    """

    evidence_cap: int = 1
    free_weight: float = 0.05
    free_evidence: str | None = None
    chord_weight: float = 0.03
    inducing_spacing: float | None = None
    max_inducing_per_axis: int | None = None
    clear_margin: float | None = None
    tile_voxels: int | None = None
    min_inducing_per_axis: int | None = None
    fill_voxels: int | None = None
    sweep_angle: float | None = None

    def __post_init__(self) -> None:
        _integer("LatticeConfig", "evidence_cap", self.evidence_cap, 1, 255)
        if self.sweep_angle is not None:
            _positive("LatticeConfig", "sweep_angle", self.sweep_angle, allow_zero=True, high=90.0)
        if self.fill_voxels is not None:
            _integer("LatticeConfig", "fill_voxels", self.fill_voxels, -1, 1 << 15)
        _positive("LatticeConfig", "free_weight", self.free_weight, low=1e-6, high=1e6)
        _positive("LatticeConfig", "chord_weight", self.chord_weight, low=1e-6, high=1e6)
        if self.free_evidence is not None and self.free_evidence not in FREE_EVIDENCE:
            raise OctolgpError(
                f"LatticeConfig.free_evidence must be one of {FREE_EVIDENCE}, "
                f"got {self.free_evidence!r}"
            )
        if self.inducing_spacing is not None:
            _positive("LatticeConfig", "inducing_spacing", self.inducing_spacing, low=MIN_SPACING)
        if self.max_inducing_per_axis is not None:
            _integer("LatticeConfig", "max_inducing_per_axis", self.max_inducing_per_axis, 2, 16)
        if self.min_inducing_per_axis is not None:
            _integer("LatticeConfig", "min_inducing_per_axis", self.min_inducing_per_axis, 2, 16)
        if self.clear_margin is not None:
            _positive("LatticeConfig", "clear_margin", self.clear_margin, allow_zero=True)
        if self.tile_voxels is not None:
            _integer("LatticeConfig", "tile_voxels", self.tile_voxels, 1, 1 << 15)
            if self.tile_voxels & (self.tile_voxels - 1):
                raise OctolgpError(
                    f"LatticeConfig.tile_voxels must be a power of two, got {self.tile_voxels}"
                )


@dataclass(frozen=True, slots=True)
class ExactConfig:
    """The exact leaf engine's advanced settings (:mod:`octolgp.engines.exact`).

    Parameters
    ----------
    max_leaf_items : int
        A leaf with more training items than this is split into k-means clusters under
        ``PartitionConfig.max_cluster_size`` (the paper's iterative k-means); below it
        the leaf is one local GP. Default 400.
    free_voxels : int
        A leaf keeps one free piece per cube of this many voxels on an edge (by the
        piece's end); 1 keeps one per voxel.
    """

    max_leaf_items: int = 400
    free_voxels: int = 1

    def __post_init__(self) -> None:
        _integer("ExactConfig", "max_leaf_items", self.max_leaf_items, 2)
        _integer("ExactConfig", "free_voxels", self.free_voxels, 1, 64)


DEFAULT_CLEAR_SCANS = 5
"""The lattice engine's default ``clear_scans`` (see :class:`OnlineConfig`)."""

CLEAR_MARGIN_VOXELS = 5
"""The default ``clear_margin`` in voxels (see :class:`LatticeConfig`)."""

DEFAULT_FILL_VOXELS = MappingProxyType({2: 2, 3: 1})
"""The default ``fill_voxels`` per dimension, capped by the halo it may reach (see
:class:`LatticeConfig`): the most the default tiles allow (BENCHMARKS.md, "Honest
unknown")."""

DEFAULT_FREE_EVIDENCE = MappingProxyType({2: "looks", 3: "chord"})
"""The default ``free_evidence`` per dimension (see :class:`LatticeConfig`): chord shares in
3D, where a sparse scan's beams cross a leaf far apart and a voxel weighed per look lets
a long free chord outweigh the returns it passes near; looks in 2D, where chord weights
at the 3D ``chord_weight`` leave a cell at an opened door's frame reading occupied."""

DEFAULT_SWEEP_ANGLE = MappingProxyType({2: 2.5, 3: 0.0})
"""The default ``sweep_angle`` in degrees per dimension (see :class:`LatticeConfig`): in 2D,
beams up to 2.5° apart (a 1° scanner with a dropped reading between two beams, or a 2°
one, with room for the rounding of the scans' points), off in 3D: a 3D scan has no order
of its beams to take neighbours from."""

DEFAULT_NO_RETURN_RANGE = MappingProxyType({2: 10.0, 3: math.inf})
"""The default ``no_return_range`` in metres per dimension (see :class:`TrainingConfig`):
10 m in 2D, where held-out AUC was at least that of whole no-return beams on every real
log measured (BENCHMARKS.md, "Honest unknown"); whole beams in 3D, whose lidar drivers
mostly drop no-returns."""

DEFAULT_LEARN_SCANS = MappingProxyType({2: 40, 3: 5})
"""The default ``learn_scans`` per dimension (see :class:`OnlineConfig`)."""

DEFAULT_HALO = MappingProxyType({(2, "lattice"): 0.45})
"""The default ``halo`` per (dimension, engine), 0.2 where absent (see :class:`OnlineConfig`)."""

DEFAULT_INDUCING_SPACING = MappingProxyType({2: 0.4, 3: 0.5})
"""The default ``inducing_spacing`` per dimension (see :class:`LatticeConfig`)."""

DEFAULT_MAX_INDUCING = MappingProxyType({2: 12, 3: 4})
"""The default ``max_inducing_per_axis`` per dimension (see :class:`LatticeConfig`)."""

VOXELS_PER_INDUCING = MappingProxyType({2: 4 / 3, 3: 2.0})
"""Per dimension, the largest lattice spacing in voxels whatever the length scale, which
gives the default ``min_inducing_per_axis`` (see :class:`LatticeConfig`)."""


LEAF_VOXELS_LOG2 = MappingProxyType(
    {(2, "lattice"): 4, (2, "exact"): 4, (3, "lattice"): 4, (3, "exact"): 3}
)
"""The default leaf edge, log2 of voxels, per (dimension, engine) (see :class:`OnlineConfig`)."""

DEFAULT_TILE_VOXELS = MappingProxyType({2: 4, 3: 4})
"""The default ``tile_voxels`` per dimension, at most the leaf's edge; absent: the leaf's edge
(see :class:`LatticeConfig`)."""


@dataclass(frozen=True, slots=True)
class MapConfig:
    """Everything that defines a map. ``MapConfig()`` serves as is.

    A field left at ``None`` takes a default derived from the others (its section's
    docstring says which); :meth:`resolve` fills every such field in. A map resolves its
    config once, when it is made, and its file stores the resolved config whole, so a
    saved map means the same whatever defaults the code that reopens it has.

    Parameters
    ----------
    dim : int
        2 or 3. Default 3.
    resolution : float
        Voxel edge, metres, in (0, :data:`MAX_RESOLUTION`]. Default 0.1.
    hyperparameters : Hyperparameters or None
        ``None`` (default) learns them from the data; a value is used as given.
    memory_budget_mb : float or None
        Bound on the RAM held by leaves and a step's working arrays, MB (10^6 bytes), at
        most 1e12 (:data:`MAX_MEMORY_BUDGET_MB`): the leaves are held to the budget less
        the room the largest recent step needed. ``None`` (default) means no bound.
    tree_depth : int
        OctoMap key depth: keys are 16-bit, ``floor(x / resolution) + 2**(depth-1)``.
    online : OnlineConfig
        The online map: engine, leaf grid, learning, threads, forgetting.
    lattice, exact : LatticeConfig, ExactConfig
        Each leaf engine's advanced settings.
    training, partition, learning, ogm
        The batch methods' stages (also the exact engine's training data and the
        hyperparameter learning).
    """

    dim: int = 3
    resolution: float = 0.1
    hyperparameters: Hyperparameters | None = None
    memory_budget_mb: float | None = None
    tree_depth: int = 16
    training: TrainingConfig = field(default_factory=TrainingConfig)
    partition: PartitionConfig = field(default_factory=PartitionConfig)
    learning: LearningConfig = field(default_factory=LearningConfig)
    ogm: OgmConfig = field(default_factory=OgmConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    lattice: LatticeConfig = field(default_factory=LatticeConfig)
    exact: ExactConfig = field(default_factory=ExactConfig)

    def __post_init__(self) -> None:
        if type(self.dim) is not int or self.dim not in (2, 3):
            raise OctolgpError(f"MapConfig.dim must be 2 or 3, got {self.dim!r}")
        _positive("MapConfig", "resolution", self.resolution, high=MAX_RESOLUTION, unit=" m")
        if self.memory_budget_mb is not None:
            _positive(
                "MapConfig", "memory_budget_mb", self.memory_budget_mb, high=MAX_MEMORY_BUDGET_MB
            )
        _integer("MapConfig", "tree_depth", self.tree_depth, 1, 16)
        for name, kind in _SECTIONS.items():
            value = getattr(self, name)
            if value is None and name == "hyperparameters":
                continue
            if not isinstance(value, kind):
                raise OctolgpError(f"MapConfig.{name} must be a {kind.__name__}, got {value!r}")
        leaf_depth = self.leaf_depth
        if not 1 <= leaf_depth <= self.tree_depth:
            raise OctolgpError(
                f"OnlineConfig.leaf_depth must be in 1..MapConfig.tree_depth "
                f"({self.tree_depth}), got {leaf_depth}"
            )
        side = 1 << (self.tree_depth - leaf_depth)
        if self.lattice.tile_voxels is not None and self.lattice.tile_voxels > side:
            raise OctolgpError(
                f"LatticeConfig.tile_voxels must be at most the leaf's edge ({side} voxels), "
                f"got {self.lattice.tile_voxels}"
            )

    def resolve(self) -> MapConfig:
        """Fill in every derived default (``n_jobs`` excepted); return the new config.

        ``n_jobs`` stays as given: threads are a property of the machine running the
        map, not of the map. Resolving a resolved config returns an equal one.

        Raises
        ------
        OctolgpError
            On settings that do not fit together (``lattice.fill_voxels`` beyond the
            tile's halo), checked here because a config file may give the dimension
            they depend on later.
        """
        if not -1 <= self.fill_voxels <= self.fill_halo_voxels:
            what = "a leaf's" if self.online.engine == "exact" else "the tile's"
            raise OctolgpError(
                f"LatticeConfig.fill_voxels must be -1 or at most {what} halo "
                f"({self.fill_halo_voxels} voxels), got {self.fill_voxels}"
            )
        if self.dim == 3 and self.sweep_angle:
            raise OctolgpError(
                f"LatticeConfig.sweep_angle must be 0 for 3D scans (the rule is 2D's), "
                f"got {self.sweep_angle!r}"
            )
        online = dataclasses.replace(
            self.online,
            leaf_depth=self.leaf_depth,
            halo=self.halo,
            learn_scans=self.learn_scans,
            clear_scans=self.clear_scans,
            prune=self.prune,
        )
        lattice = dataclasses.replace(
            self.lattice,
            inducing_spacing=self.inducing_spacing,
            max_inducing_per_axis=self.max_inducing_per_axis,
            clear_margin=self.clear_margin,
            tile_voxels=self.tile_voxels,
            min_inducing_per_axis=self.min_inducing_per_axis,
            fill_voxels=self.fill_voxels,
            sweep_angle=self.sweep_angle,
            free_evidence=self.free_evidence,
        )
        training = dataclasses.replace(
            self.training, free_margin=self.free_margin, no_return_range=self.no_return_range
        )
        return dataclasses.replace(self, online=online, lattice=lattice, training=training)

    # The values in force: a field's own value, or its default derived from the others.
    @property
    def leaf_depth(self) -> int:
        """Tree depth of the online map's leaves (``online.leaf_depth`` or its default)."""
        if self.online.leaf_depth is not None:
            return self.online.leaf_depth
        return self.tree_depth - LEAF_VOXELS_LOG2[(self.dim, self.online.engine)]

    @property
    def halo(self) -> float:
        """Leaf (or tile) overlap as a fraction of its edge (``online.halo`` or its default)."""
        if self.online.halo is not None:
            return self.online.halo
        return DEFAULT_HALO.get((self.dim, self.online.engine), 0.2)

    @property
    def n_jobs(self) -> int:
        """Leaf-fitting threads: ``online.n_jobs``, or the usable CPU cores (at most 8)."""
        if self.online.n_jobs is not None:
            return self.online.n_jobs
        if hasattr(os, "sched_getaffinity"):
            return max(1, min(8, len(os.sched_getaffinity(0))))
        return max(1, min(8, os.cpu_count() or 1))

    @property
    def inducing_spacing(self) -> float:
        """Lattice spacing over length scale (``lattice.inducing_spacing`` or its default)."""
        if self.lattice.inducing_spacing is not None:
            return self.lattice.inducing_spacing
        return DEFAULT_INDUCING_SPACING[self.dim]

    @property
    def min_inducing_per_axis(self) -> int:
        """Fewest lattice points per axis (``lattice.min_inducing_per_axis`` or its default)."""
        if self.lattice.min_inducing_per_axis is not None:
            return self.lattice.min_inducing_per_axis
        box = self.tile_voxels + 2 * self.tile_halo_voxels
        k = math.ceil(box / VOXELS_PER_INDUCING[self.dim] - 1e-9)
        return max(2, min(self.max_inducing_per_axis, k))

    @property
    def fill_voxels(self) -> int:
        """Voxels from an observed one within which the GP fills (or its default)."""
        if self.lattice.fill_voxels is not None:
            return self.lattice.fill_voxels
        return min(DEFAULT_FILL_VOXELS[self.dim], self.fill_halo_voxels)

    @property
    def fill_halo_voxels(self) -> int:
        """The most ``fill_voxels`` may be: the halo, in whole voxels, of what the engine fits.

        A lattice tile's (:attr:`tile_halo_voxels`); an exact leaf's, ``halo`` of the
        leaf's edge rounded up (its halo box holds every voxel that counts).
        """
        if self.online.engine == "exact":
            side = 1 << (self.tree_depth - self.leaf_depth)
            return math.ceil(self.halo * side - 1e-9)
        return self.tile_halo_voxels

    @property
    def free_evidence(self) -> str:
        """How a lattice leaf weighs its free voxels (``lattice.free_evidence`` or its default)."""
        if self.lattice.free_evidence is not None:
            return self.lattice.free_evidence
        return DEFAULT_FREE_EVIDENCE[self.dim]

    @property
    def sweep_angle(self) -> float:
        """Degrees between two beams whose sector counts as seen (or its default; 0: off)."""
        if self.lattice.sweep_angle is not None:
            return float(self.lattice.sweep_angle)
        return DEFAULT_SWEEP_ANGLE[self.dim]

    @property
    def tile_halo_voxels(self) -> int:
        """Whole voxels of overlap around a lattice tile: ``halo`` of its edge, rounded up."""
        return math.ceil(self.halo * self.tile_voxels - 1e-9)

    @property
    def max_inducing_per_axis(self) -> int:
        """Cap on lattice points per axis (``lattice.max_inducing_per_axis`` or its default)."""
        if self.lattice.max_inducing_per_axis is not None:
            return self.lattice.max_inducing_per_axis
        return DEFAULT_MAX_INDUCING[self.dim]

    @property
    def prune(self) -> bool:
        """Whether confident leaves keep one value (``online.prune`` or its default)."""
        if self.online.prune is not None:
            return self.online.prune
        return not (self.dim == 3 and self.online.engine == "lattice")

    @property
    def tile_voxels(self) -> int:
        """Edge of the lattice engine's GP tiles (``lattice.tile_voxels`` or its default)."""
        side = 1 << (self.tree_depth - self.leaf_depth)
        if self.lattice.tile_voxels is not None:
            return self.lattice.tile_voxels
        return min(DEFAULT_TILE_VOXELS.get(self.dim, side), side)

    @property
    def clear_scans(self) -> int:
        """Free looks that forget a voxel's returns (``online.clear_scans`` or its default)."""
        if self.online.clear_scans is not None:
            return self.online.clear_scans
        return DEFAULT_CLEAR_SCANS if self.online.engine == "lattice" else 0

    @property
    def clear_margin(self) -> float:
        """Metres before a return that do not count towards forgetting (or 5 voxels)."""
        if self.lattice.clear_margin is not None:
            return self.lattice.clear_margin
        return CLEAR_MARGIN_VOXELS * self.resolution

    @property
    def learn_scans(self) -> int:
        """Scans buffered to learn hyperparameters on (``online.learn_scans`` or its default)."""
        if self.online.learn_scans is not None:
            return self.online.learn_scans
        return DEFAULT_LEARN_SCANS[self.dim]

    @property
    def free_margin(self) -> float:
        """Metres a free segment stops short of its hit (``training.free_margin`` or one voxel)."""
        margin = self.training.free_margin
        return self.resolution if margin is None else margin

    @property
    def free_range(self) -> float:
        """Metres a beam's evidence reaches (``training.free_range``)."""
        return float(self.training.free_range)

    @property
    def no_return_range(self) -> float:
        """Metres a no-return beam is free up to (``training.no_return_range`` or default)."""
        r = self.training.no_return_range
        return min(DEFAULT_NO_RETURN_RANGE[self.dim] if r is None else float(r), self.free_range)

    def to_dict(self) -> dict[str, Any]:
        """Return the config as nested plain dicts (``None`` values dropped, TOML-ready).

        ``resolve().to_dict()`` holds every field but ``n_jobs`` when not given.
        """

        def strip(d: dict[str, Any]) -> dict[str, Any]:
            return {
                k: strip(v) if isinstance(v, dict) else v for k, v in d.items() if v is not None
            }

        return strip(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapConfig:
        """Build a config from nested dicts, as read from TOML or JSON.

        Raises
        ------
        OctolgpError
            On an unknown key (``MapConfig.online.clear_scan: unknown key``) or a bad value
            (naming the field, as the section's validation does).
        """
        return cls._from_dict(data, "MapConfig.", toml_names=False)

    @classmethod
    def _from_dict(cls, data: dict[str, Any], where: str, *, toml_names: bool) -> MapConfig:
        """:meth:`from_dict`; errors start with ``where``, keys named as in TOML if asked."""
        kwargs: dict[str, Any] = {}
        valid = [f.name for f in dataclasses.fields(cls)]
        data = _migrate(data, where)
        for key, value in data.items():
            if key not in valid:
                raise OctolgpError(f"{where}{key}: unknown key (keys: {', '.join(valid)})")
            section = _SECTIONS.get(key)
            if section is not None:
                if not isinstance(value, dict):
                    raise OctolgpError(
                        f"{where}{key}: must be a table of {section.__name__} fields, got {value!r}"
                    )
                names = [f.name for f in dataclasses.fields(section)]
                for sub in value:
                    if sub not in names:
                        raise OctolgpError(
                            f"{where}{key}.{sub}: unknown key (keys: {', '.join(names)})"
                        )
                try:
                    value = section(**value)
                except OctolgpError as exc:
                    if not toml_names:
                        raise
                    raise OctolgpError(where + _toml_named(str(exc))) from None
            kwargs[key] = value
        try:
            return cls(**kwargs)
        except OctolgpError as exc:
            if not toml_names:
                raise
            raise OctolgpError(where + _toml_named(str(exc))) from None

    @classmethod
    def from_toml(cls, path: str | Path) -> MapConfig:
        """Read a config from a TOML file: top-level fields, then one table per section.

        Keys left out take their defaults (:meth:`to_toml` writes them all).

        Raises
        ------
        MapFileNotFound
            If ``path`` does not exist.
        OctolgpError
            On invalid TOML, an unknown key or a bad value, naming the file and the key,
            and the key's line where it is written as ``key = value`` under its table
            (``cfg.toml: online.clear_scan: unknown key (keys: ...) (line 4)``).
        """
        p = Path(path)
        if not p.is_file():
            raise MapFileNotFound(f"config file {str(p)!r} does not exist")
        try:
            text = p.read_text()
            data = tomllib.loads(text)
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise OctolgpError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
        try:
            return cls._from_dict(data, "", toml_names=True)
        except OctolgpError as exc:
            line = _toml_line(text, str(exc))
            at = "" if line is None else f" (line {line})"
            raise OctolgpError(f"config file {str(p)!r}: {exc}{at}") from None

    def to_toml(self) -> str:
        """The config as TOML that :meth:`from_toml` reads back to an equal config.

        Every field is written (``None`` values, meaning "derived", are left out), top-level
        fields first, then one table per section, in declaration order.
        """
        lines = ["# octolgp MapConfig: read with `--config FILE` or MapConfig.from_toml"]
        tables = []
        for key, value in self.to_dict().items():
            if isinstance(value, dict):
                tables.append((key, value))
            else:
                lines.append(f"{key} = {_toml_value(value)}")
        for key, table in tables:
            lines += ["", f"[{key}]"]
            lines += [f"{name} = {_toml_value(v)}" for name, v in table.items()]
            if key == "online" and self.online.n_jobs is None:
                lines.append("# n_jobs: unset, the usable CPU cores (at most 8) when the map runs")
        return "\n".join(lines) + "\n"


_SECTIONS: MappingProxyType[str, type] = MappingProxyType(
    {
        "hyperparameters": Hyperparameters,
        "training": TrainingConfig,
        "partition": PartitionConfig,
        "learning": LearningConfig,
        "ogm": OgmConfig,
        "online": OnlineConfig,
        "lattice": LatticeConfig,
        "exact": ExactConfig,
    }
)
"""The sections of :class:`MapConfig`: TOML table name -> dataclass."""

_MOVED = MappingProxyType(
    {
        ("online", "evidence_cap"): "lattice",
        ("online", "free_weight"): "lattice",
        ("online", "inducing_spacing"): "lattice",
        ("online", "max_inducing_per_axis"): "lattice",
        ("online", "clear_margin"): "lattice",
        ("online", "max_leaf_items"): "exact",
        ("online", "free_voxels"): "exact",
    }
)
"""Keys of earlier configs (map files, TOML files) that now live in another section."""

_FIXED = MappingProxyType(
    {
        ("online", "prune_free"): 0.1192,
        ("online", "prune_occupied"): 0.971,
        ("online", "kernel_cache_mb"): 64.0,
        ("learning", "balance_classes"): False,
        ("learning", "min_noise_variance"): 1e-2,
    }
)
"""Keys of earlier configs that are constants now, with the one value they still accept."""


def _migrate(data: dict[str, Any], where: str) -> dict[str, Any]:
    """A config dict of an earlier layout in today's sections (a new dict).

    Moved keys go to their section; a fixed key is dropped when it holds its constant's
    value and refused otherwise; ``online.max_inducing_per_axis = 0`` meant "derived".
    """
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for (section, key), target in _MOVED.items():
        table = out.get(section)
        if isinstance(table, dict) and key in table:
            value = table.pop(key)
            if key == "max_inducing_per_axis" and value == 0:
                continue
            moved = out.setdefault(target, {})
            if isinstance(moved, dict):
                moved.setdefault(key, value)
    for (section, key), fixed in _FIXED.items():
        table = out.get(section)
        if isinstance(table, dict) and key in table:
            value = table.pop(key)
            if value != fixed:
                raise OctolgpError(
                    f"{where}{section}.{key}: no longer a setting (fixed at {fixed!r}), got "
                    f"{value!r}"
                )
    return out


def _toml_named(message: str) -> str:
    """A validation message with its leading ``OnlineConfig.`` as ``online.`` (TOML keys)."""
    if message.startswith("MapConfig."):
        return message[len("MapConfig.") :]
    for key, section in _SECTIONS.items():
        if message.startswith(section.__name__ + "."):
            return key + message[len(section.__name__) :]
    return message


_KEY_PATH = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\.([A-Za-z_][A-Za-z0-9_]*))?[ :]")
_TABLE = re.compile(r"\s*\[\s*([A-Za-z0-9_]+)\s*\]\s*(?:#.*)?$")


def _toml_line(text: str, message: str) -> int | None:
    """The 1-based line of TOML ``text`` that sets the key a message starts with, if found.

    ``message`` starts with a TOML key path, ``resolution`` or ``online.halo``; the key is
    found as ``key = ...`` at the top level or under its ``[section]`` header (inline
    tables and dotted keys are not looked into).
    """
    found = _KEY_PATH.match(message)
    if found is None:
        return None
    section, key = (None, found[1]) if found[2] is None else (found[1], found[2])
    setting = re.compile(rf"\s*[\"']?{re.escape(key)}[\"']?\s*=")
    table: str | None = None
    for number, line in enumerate(text.splitlines(), start=1):  # one iteration per line
        header = _TABLE.match(line)
        if header is not None:
            table = header[1]
        elif table == section and setting.match(line):
            return number
    return None


def _toml_value(value: object) -> str:
    """One TOML value: a bool, int, float or string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    raise TypeError(f"cannot write {value!r} to TOML")
