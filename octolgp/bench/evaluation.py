"""``octolgp eval``: the held-out-scan protocol run for every method on one log.

For each seed (or, with ``leave_one_out``, for each scan):

1. :func:`~octolgp.bench.heldout.heldout_split` holds out ``fraction`` of the scans in
   contiguous runs of at most ``run`` scans;
2. the held-out beams become labelled test points: with ``protocol="endpoint"``
   (:func:`~octolgp.bench.heldout.heldout_points`) each endpoint occupied and one point
   drawn uniformly along each beam up to ``short`` metres before the hit free; with
   ``protocol="hilbert"`` (:func:`~octolgp.bench.heldout.hilbert_points`, the protocol of
   Hilbert maps' reference code) each return's endpoint occupied and ``max(1, int(d/2))``
   points uniform on ``[0, d - short]`` free;
3. every method maps the training scans only, with the same hyperparameters
   (learnt once per split on the first ``learn_scans`` training scans, as the online
   map does, unless the config gives them):

   - ``online``: :class:`~octolgp.mapping.online.OnlineMap`, scans inserted one by one;
   - ``batch``: ``build_map(method="lgp")``, the paper's offline overlapping local GPs;
   - ``grid``: ``build_map(method="ogm")``, the log-odds occupancy grid baseline;
   - ``octomap``: the real OctoMap library (:mod:`~octolgp.bench.octomap_ref`), when
     ``pyoctomap`` is installed (skipped otherwise, and said so in the report);

4. each map's ``P(occupied)`` at the test points gives the ROC AUC (unknown points
   scored 0.5) and the fraction of test points it leaves unknown (exactly 0.5).

The report holds per-split numbers, mean ± std per method, build seconds and the ROC
curve of every method on every split; :func:`plot_roc` draws them.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sklearn.metrics import roc_curve

from octolgp.bench.heldout import (
    PROTOCOLS,
    auc,
    heldout_points,
    heldout_split,
    hilbert_points,
    novel_fraction,
    seen_free_fraction,
    unknown_fraction,
)
from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.mapping.evidence import map_scans
from octolgp.scan import Scan

FloatArray = NDArray[np.float64]

NOVEL_RADIUS = 0.3
"""Metres: an occupied test point this far from every training return is a wall only the
held-out scans hit (:attr:`EvalReport.novel`)."""

CROP_MARGIN = 2.0
"""Metres of map drawn around the middle 99 % of the test points in ``errors.png``."""

METHODS = ("online", "batch", "grid", "octomap")
"""Method names of :func:`evaluate_log`, in report order."""

LABELS = MappingProxyType(
    {
        "online": "octolgp online",
        "batch": "octolgp batch (lgp)",
        "grid": "grid (ogm)",
        "octomap": "OctoMap",
    }
)
"""Display name of each method."""

ROC_POINTS = 200
"""ROC curves are resampled to this many false-positive rates (keeps reports small)."""


@dataclass(frozen=True, slots=True)
class SplitResult:
    """One method on one split.

    Attributes
    ----------
    auc : float
        ROC AUC over all test points, unknown points scored 0.5.
    unknown_fraction : float
        Share of test points the map leaves at exactly 0.5.
    seconds : float
        Wall time to build the map from the training scans.
    fpr, tpr : ndarray of shape (ROC_POINTS,)
        The ROC curve, resampled at evenly spaced false-positive rates.
    """

    auc: float
    unknown_fraction: float
    seconds: float
    fpr: FloatArray
    tpr: FloatArray


@dataclass(frozen=True)
class ExampleSplit:
    """What the pictures of ``octolgp eval --out`` show: the worst split's first GP map.

    Attributes
    ----------
    split, method : str
        Which split and method the map and scores are.
    resolution : float
        Voxel edge, metres.
    centres : ndarray of shape (k, d)
        The map's voxel centres, world frame, metres.
    prob : ndarray of shape (k,)
        P(occupied) per voxel.
    points : ndarray of shape (m, d)
        The split's held-out test points.
    labels : ndarray of int8, shape (m,)
        1 occupied, 0 free.
    scores : ndarray of shape (m,)
        The map's P(occupied) at the test points.
    auc : float
        The map's AUC on this split, the lowest of its method's splits.
    """

    split: str
    method: str
    resolution: float
    centres: FloatArray
    prob: FloatArray
    points: FloatArray
    labels: NDArray[np.int8]
    scores: FloatArray
    auc: float = float("nan")


@dataclass
class EvalReport:
    """Everything :func:`evaluate_log` measured.

    Attributes
    ----------
    splits : list of str
        Split names (``seed 0``, ... or ``scan 3``, ...).
    n_points, n_occupied : list of int
        Test points per split, and how many are occupied.
    results : dict
        ``method -> list of SplitResult``, one per split, in :data:`METHODS` order.
    skipped : dict
        ``method -> reason`` for methods that could not run (OctoMap not installed).
    hyperparameters : list of Hyperparameters
        The ones every method used, per split.
    novel : list of float
        Per split, the share of occupied test points with no training return within
        :data:`NOVEL_RADIUS` metres (:func:`~octolgp.bench.heldout.novel_fraction`): walls
        only the held-out scans hit, which bounds what any method can score.
    seen_free : list of float
        Per split, the share of occupied test points among those whose voxel a training
        beam's free segment crossed (:func:`~octolgp.bench.heldout.seen_free_fraction`):
        the training scans looked through where the held-out scans hit something.
    """

    splits: list[str] = field(default_factory=list)
    n_points: list[int] = field(default_factory=list)
    n_occupied: list[int] = field(default_factory=list)
    results: dict[str, list[SplitResult]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    hyperparameters: list[Hyperparameters] = field(default_factory=list)
    novel: list[float] = field(default_factory=list)
    seen_free: list[float] = field(default_factory=list)
    example: ExampleSplit | None = None

    def summary(self) -> dict[str, dict[str, float]]:
        """Mean and standard deviation (ddof 0) of AUC, unknown fraction and seconds per method."""
        out: dict[str, dict[str, float]] = {}
        for method, rows in self.results.items():
            aucs = np.array([r.auc for r in rows])
            unk = np.array([r.unknown_fraction for r in rows])
            secs = np.array([r.seconds for r in rows])
            out[method] = {
                "auc_mean": float(aucs.mean()),
                "auc_std": float(aucs.std()),
                "auc_worst": float(aucs.min()),
                "unknown_mean": float(unk.mean()),
                "unknown_std": float(unk.std()),
                "seconds_mean": float(secs.mean()),
            }
        return out

    def table(self) -> str:
        """A markdown table: one row per method, AUC mean ± std, unknown fraction, build s."""
        lines = [
            f"{len(self.splits)} splits, {int(np.mean(self.n_points)) if self.n_points else 0} "
            "test points per split on average",
            "",
            "| method | AUC (mean ± std) | worst split | unknown fraction | build s (mean) |",
            "|---|---|---|---|---|",
        ]
        for method, s in self.summary().items():
            lines.append(
                f"| {LABELS[method]} | {s['auc_mean']:.4f} ± {s['auc_std']:.4f} | "
                f"{s['auc_worst']:.4f} | {s['unknown_mean']:.3f} | {s['seconds_mean']:.1f} |"
            )
        for method, why in self.skipped.items():
            lines.append(f"| {LABELS[method]} | not run: {why} | | | |")
        if self.novel:
            shares = ", ".join(f"{x:.2f}" for x in self.novel)
            lines += [
                "",
                f"occupied test points with no training return within {NOVEL_RADIUS} m, "
                f"per split: {shares}",
            ]
        if self.seen_free:
            shares = ", ".join(f"{x:.2f}" for x in self.seen_free)
            lines.append(f"of them, in voxels the training scans saw free, per split: {shares}")
        if self.hyperparameters:
            lines += [
                "",
                f"learnt hyperparameters over the {len(self.splits)} splits (mean ± std):",
            ]
            for name, (mean, std) in self.hyperparameter_spread().items():
                lines.append(f"- {name}: {mean:.3g} ± {std:.2g}")
        return "\n".join(lines)

    def hyperparameter_spread(self) -> dict[str, tuple[float, float]]:
        """Mean and standard deviation (ddof 0) of each hyperparameter over the splits."""
        rows = [dataclasses.asdict(hp) for hp in self.hyperparameters]
        return {
            name: (float(np.mean([r[name] for r in rows])), float(np.std([r[name] for r in rows])))
            for name in (rows[0] if rows else {})
        }

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (no ROC arrays)."""
        return {
            "splits": self.splits,
            "n_points": self.n_points,
            "n_occupied": self.n_occupied,
            "summary": self.summary(),
            "per_split": {
                m: [
                    {"auc": r.auc, "unknown_fraction": r.unknown_fraction, "seconds": r.seconds}
                    for r in rows
                ]
                for m, rows in self.results.items()
            },
            "skipped": self.skipped,
            "hyperparameters": [dataclasses.asdict(hp) for hp in self.hyperparameters],
            "novel": self.novel,
            "seen_free": self.seen_free,
        }


def _check_methods(methods: Sequence[str]) -> tuple[str, ...]:
    """Validate method names; return them in :data:`METHODS` order, without repeats."""
    if isinstance(methods, str):
        raise OctolgpError("methods must be a sequence of names, not one string")
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        raise OctolgpError(
            f"methods: unknown {unknown or 'empty list'} (choose from {', '.join(METHODS)})"
        )
    return tuple(m for m in METHODS if m in set(methods))


def _roc(labels: NDArray[np.int8], probs: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The ROC curve resampled at :data:`ROC_POINTS` evenly spaced false-positive rates."""
    fpr, tpr, _ = roc_curve(labels, probs)
    grid = np.linspace(0.0, 1.0, ROC_POINTS)
    return grid, np.interp(grid, fpr, tpr)


def _builders(
    config: MapConfig, n_jobs: int, fast_online: bool
) -> dict[str, Callable[[list[Scan]], Any]]:
    """One function per method: training scans -> a map with ``occupancy(points)``."""
    from octolgp.batch.build import build_map
    from octolgp.bench.octomap_ref import OctomapReference
    from octolgp.mapping.online import OnlineMap

    def online(train: list[Scan]) -> Any:
        if fast_online:
            from octolgp.batch.leafmap import build_tiled

            return build_tiled(train, config, n_jobs=n_jobs)
        cfg = dataclasses.replace(config, online=dataclasses.replace(config.online, n_jobs=n_jobs))
        m = OnlineMap(cfg)
        for s in train:
            m.insert_scan(s)
        m.flush()
        return m

    def octomap(train: list[Scan]) -> Any:
        ref = OctomapReference(config.resolution, config.dim)
        for s in train:
            ref.insert_scan(s)
        return ref

    return {
        "online": online,
        "batch": lambda train: build_map(train, config, method="lgp", n_jobs=n_jobs),
        "grid": lambda train: build_map(train, config, method="ogm"),
        "octomap": octomap,
    }


def evaluate_log(
    scans: Sequence[Scan],
    config: MapConfig,
    *,
    seeds: int = 5,
    fraction: float = 0.1,
    run: int = 40,
    short: float = 0.1,
    leave_one_out: bool = False,
    methods: Sequence[str] = METHODS,
    n_jobs: int = 1,
    downsample: float | None = None,
    progress: Callable[[str], None] | None = None,
    fast_online: bool = False,
    protocol: str = "endpoint",
) -> EvalReport:
    """Run the held-out-scan protocol on a log for several methods.

    Parameters
    ----------
    scans : sequence of Scan
        The whole log, world frame, all of dimension ``config.dim``; at least 2 scans.
    config : MapConfig
        Map settings for every method (resolution, dimension). With
        ``hyperparameters=None`` they are learnt per split on the first
        ``config.learn_scans`` training scans and shared by the GP methods.
    seeds : int
        Number of random splits (seeds ``0 .. seeds-1``), ``>= 1``.
    fraction, run : float, int
        Held-out share and longest run of consecutive held-out scans
        (see :func:`~octolgp.bench.heldout.heldout_split`).
    short : float
        Metres between the last free test point and the hit, ``>= 0``.
    leave_one_out : bool
        Instead of random splits, hold out each scan once (for logs of a few big scans,
        such as the 3DTK set); ``seeds``, ``fraction`` and ``run`` are then unused.
    methods : sequence of str
        Any of :data:`METHODS`; ``"octomap"`` is skipped (and reported) without
        ``pyoctomap``.
    n_jobs : int
        Threads over leaves/clusters for the GP methods.
    downsample : float, optional
        Voxel edge (metres) of a voxel-grid filter applied to the training scans of
        every method (:meth:`Scan.downsample`); test points come from the raw
        held-out scans.
    progress : callable, optional
        Called with a short message before each map build.
    fast_online : bool
        Build the ``online`` map in one step (:func:`octolgp.batch.leafmap.build_tiled`): the
        same map as inserting the training scans one by one, bit for bit (tested), in a
        fraction of the time; its ``seconds`` are then those of the one-step build.
    protocol : {"endpoint", "hilbert"}
        The held-out test points (module docstring, step 2).

    Returns
    -------
    EvalReport

    Raises
    ------
    OctolgpError
        On fewer than 2 scans, mixed dimensions, bad method names or bad numbers.
    """
    from octolgp.gp.learning import learn_hyperparameters

    scan_list = list(scans)
    wanted = _check_inputs(scan_list, config, methods, seeds, protocol, downsample)
    report = EvalReport()
    wanted = _drop_unavailable(report, wanted)
    report.results = {m: [] for m in wanted}
    splits = _splits(len(scan_list), leave_one_out, seeds, fraction, run)
    for index, (name, train_idx, test_idx) in enumerate(splits):
        test = [scan_list[i] for i in test_idx]
        points, labels = _test_points(test, protocol, index, short)
        train = [scan_list[i] for i in train_idx]
        if downsample is not None:
            train = [s.downsample(downsample) for s in train]
        hp = config.hyperparameters
        if hp is None:
            if progress:
                progress(f"{name}: learning hyperparameters")
            hp = learn_hyperparameters(map_scans(train[: config.learn_scans], config), config)
        fixed = dataclasses.replace(config, hyperparameters=hp)
        builders = _builders(fixed, n_jobs, fast_online)
        _record_split(report, name, train, points, labels, hp, config)
        for method in wanted:
            if progress:
                progress(f"{name}: {LABELS[method]} on {len(train)} scans")
            t0 = time.perf_counter()
            built = builders[method](train)
            seconds = time.perf_counter() - t0
            _score_map(report, built, seconds, name, method, config.resolution, points, labels)
    return report


def _check_inputs(
    scan_list: list[Scan],
    config: MapConfig,
    methods: Sequence[str],
    seeds: int,
    protocol: str,
    downsample: float | None,
) -> tuple[str, ...]:
    """Validate :func:`evaluate_log`'s arguments; return the wanted methods in report order.

    Raises
    ------
    OctolgpError
        On fewer than 2 scans, mixed dimensions, bad method names or bad numbers.
    """
    if len(scan_list) < 2:
        raise OctolgpError(f"eval: needs at least 2 scans, got {len(scan_list)}")
    if any(s.dim != config.dim for s in scan_list):
        raise OctolgpError(f"eval: every scan must have dimension {config.dim}")
    wanted = _check_methods(methods)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise OctolgpError(f"eval: seeds must be an integer >= 1, got {seeds!r}")
    if protocol not in PROTOCOLS:
        raise OctolgpError(
            f"eval: protocol must be one of {', '.join(PROTOCOLS)}, got {protocol!r}"
        )
    if downsample is not None and not (math.isfinite(downsample) and downsample > 0):
        raise OctolgpError(f"eval: downsample must be a finite number > 0, got {downsample!r}")
    return wanted


def _drop_unavailable(report: EvalReport, wanted: tuple[str, ...]) -> tuple[str, ...]:
    """Drop ``octomap`` from ``wanted`` without ``pyoctomap``, noting why in ``report``."""
    from octolgp.bench.octomap_ref import octomap_available

    if "octomap" in wanted and not octomap_available():
        report.skipped["octomap"] = "pyoctomap is not installed (pip install octolgp[octomap])"
        wanted = tuple(m for m in wanted if m != "octomap")
    return wanted


def _splits(
    n: int, leave_one_out: bool, seeds: int, fraction: float, run: int
) -> list[tuple[str, Any, Any]]:
    """The splits of ``n`` scans as ``(name, train indices, test indices)``.

    With ``leave_one_out`` each scan is held out once; otherwise each seed draws one
    :func:`~octolgp.bench.heldout.heldout_split`.
    """
    if leave_one_out:
        return [(f"scan {i}", np.delete(np.arange(n), i), np.array([i])) for i in range(n)]
    return [
        (f"seed {seed}", *heldout_split(n, fraction=fraction, run=run, seed=seed))
        for seed in range(seeds)
    ]


def _test_points(
    test: list[Scan], protocol: str, index: int, short: float
) -> tuple[FloatArray, NDArray[np.int8]]:
    """The labelled test points of split ``index``'s held-out scans under ``protocol``."""
    if protocol == "hilbert":
        return hilbert_points(test, np.random.default_rng(index), short)
    return heldout_points(test, np.random.default_rng(index), 1, short)


def _record_split(
    report: EvalReport,
    name: str,
    train: list[Scan],
    points: FloatArray,
    labels: NDArray[np.int8],
    hp: Hyperparameters,
    config: MapConfig,
) -> None:
    """Append one split's name, test-point counts, novelty shares and hyperparameters."""
    report.splits.append(name)
    report.n_points.append(int(labels.size))
    report.n_occupied.append(int(np.count_nonzero(labels)))
    report.novel.append(novel_fraction(train, points[labels == 1], NOVEL_RADIUS))
    report.seen_free.append(seen_free_fraction(train, points[labels == 1], NOVEL_RADIUS, config))
    report.hyperparameters.append(hp)


def _score_map(
    report: EvalReport,
    built: Any,
    seconds: float,
    name: str,
    method: str,
    resolution: float,
    points: FloatArray,
    labels: NDArray[np.int8],
) -> None:
    """Score one built map on the test points and append its :class:`SplitResult`.

    The map becomes :attr:`EvalReport.example` when it has voxels and is its method's
    worst split so far (or the first map with voxels); it is closed once scored.
    """
    probs = np.asarray(built.occupancy(points), dtype=np.float64)
    score = auc(labels, probs)
    shown = report.example
    if hasattr(built, "voxels") and (  # the pictures: the worst split's map
        shown is None or (shown.method == method and score < shown.auc)
    ):
        centres, prob = built.voxels()
        report.example = ExampleSplit(
            name, method, resolution, centres, prob, points, labels, probs, score
        )
    close = getattr(built, "close", None)
    if close is not None:
        close()
    fpr, tpr = _roc(labels, probs)
    report.results[method].append(SplitResult(score, unknown_fraction(probs), seconds, fpr, tpr))


def plot_roc(report: EvalReport, path: str | Path, title: str = "") -> None:
    """Draw every method's ROC curves (one thin line per split, mean curve thick) as a PNG.

    Parameters
    ----------
    report : EvalReport
    path : str or Path
        Output ``.png``; its folder is created.
    title : str
        Figure title (the log's name, say).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 5))
    summary = report.summary()
    for i, (method, rows) in enumerate(report.results.items()):
        colour = f"C{i}"
        for r in rows:
            ax.plot(r.fpr, r.tpr, color=colour, lw=0.5, alpha=0.35)
        mean_tpr = np.mean([r.tpr for r in rows], axis=0)
        s = summary[method]
        ax.plot(
            rows[0].fpr,
            mean_tpr,
            color=colour,
            lw=2,
            label=f"{LABELS[method]}: AUC {s['auc_mean']:.4f} ± {s['auc_std']:.4f}",
        )
    ax.plot([0, 1], [0, 1], color="0.7", lw=0.8, ls="--")
    ax.set_xlabel("false-positive rate (free called occupied)")
    ax.set_ylabel("true-positive rate (occupied found)")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.01)
    ax.set_title(title or "held-out scans: ROC")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def plot_errors(example: ExampleSplit, path: str | Path, title: str = "") -> None:
    """The example map with its held-out points coloured by error, as a PNG (2D maps).

    Free points the map calls occupied (P > 0.5) are red, occupied points it calls free
    (P < 0.5) blue, points it leaves unknown (P = 0.5) orange; correct points are not
    drawn. The view is cropped to the test points (:data:`CROP_MARGIN`). A 3D map is
    drawn as its slice at the median test-point height.

    Parameters
    ----------
    example : ExampleSplit
    path : str or Path
        Output ``.png``; its folder is created.
    title : str
        Figure title.
    """
    from matplotlib.figure import Figure

    from octolgp.export.image import occupancy_raster

    centres, prob, points = example.centres, example.prob, example.points
    if centres.shape[1] == 3:  # one height slice
        z = float(np.median(points[:, 2]))
        res = example.resolution
        keep = np.floor(centres[:, 2] / res) == np.floor(z / res)
        near = np.abs(points[:, 2] - z) < res
        centres, prob = centres[keep, :2], prob[keep]
        points, labels, scores = points[near, :2], example.labels[near], example.scores[near]
    else:
        labels, scores = example.labels, example.scores
    fig = Figure(figsize=(8.0, 8.0), dpi=120, layout="constrained")
    ax = fig.add_subplot()
    if centres.shape[0]:
        grid, extent = occupancy_raster(centres, prob, example.resolution)
        ax.imshow(grid, origin="lower", extent=extent, cmap="gray_r", vmin=0, vmax=1, alpha=0.6)
    kinds = (
        ((labels == 0) & (scores > 0.5), "red", "free read occupied"),
        ((labels == 1) & (scores < 0.5), "blue", "occupied read free"),
        (scores == 0.5, "orange", "unknown (0.5)"),
    )
    for mask, colour, name in kinds:
        ax.scatter(
            points[mask, 0], points[mask, 1], s=2, c=colour, label=f"{name}: {int(mask.sum())}"
        )
    if points.shape[0]:  # the test points' region, not the reach of no-return rays
        low, high = np.percentile(points, [0.5, 99.5], axis=0)
        ax.set_xlim(low[0] - CROP_MARGIN, high[0] + CROP_MARGIN)
        ax.set_ylim(low[1] - CROP_MARGIN, high[1] + CROP_MARGIN)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8, markerscale=4)
    ax.set_title(title or f"{example.split}, {LABELS[example.method]}: held-out errors")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
