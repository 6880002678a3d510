"""Live-3D benchmark: octolgp against OctoMap and DUFOMap on the same 3D lidar scans, every scene.

Figures: BENCHMARKS.md, "Lattice engine", 3D.

What it measures, per scene: the median and p90 ``insert_scan`` time of octolgp once
its hyperparameters are known (the learning step on its own row), of OctoMap
(``pyoctomap``'s ``insertPointCloud`` through :mod:`octolgp.bench.octomap_ref`) and of
DUFOMap (``dufomap``'s ``run`` through :mod:`octolgp.bench.dufomap_ref`, the physical
reference for integrating one scan's rays); the ratios octolgp / OctoMap and octolgp /
DUFOMap; the peak RSS of the process while the three maps are alive; the held-out AUC
of octolgp, of OctoMap and of octolgp's exact engine (``online.engine="exact"``, the
same hyperparameters, inserted on the same scans afterwards and timed on its own). A
one-line verdict per scene checks the goals: median insert at most 1x OctoMap's, AUC at
least the exact engine's - 0.002 and at least OctoMap's + 0.003.

The same points: every mapper gets exactly ``scan.downsample(0.2)``'s points and
origin, and the three are inserted alternately scan by scan in one process (the
order rotates with the scan), each call timed with ``time.perf_counter``. octolgp is
``OnlineMap(MapConfig(dim=3, resolution=0.2))``, the configuration a user gets
(lattice engine, forgetting on, hyperparameters learnt once ``learn_scans`` scans are
buffered), changed only by the options (the header lists every change).

Scenes (``--scenes``, default all):

- ``room``: ``octolgp.sim.lidar3d.simulate_lidar_room``, a 20 x 20 x 5 m room of 22
  boxes, a 32 x 1024 lidar (±15°, 30 m) at ``--scans`` poses on a loop; held out:
  ``--heldout`` extra poses labelled against the exact boxes
  (``LidarRoom.heldout_points``).
- ``street32``, ``street64``: the car-lidar case, ``octolgp.sim.mission.simulate_mission3d``
  (a street of buildings, fences, poles and trees on a flat ground), a 32 x 1024
  (±15°) and a 64 x 1024 (-24.9°..+2°, like an HDL-64E) lidar 1 m above the road, ranges
  to 80 m, ``--street-scans`` scans 1 m apart on a straight stretch. Held out:
  ``--street-heldout`` poses between the training poses (a seeded lateral offset of up to
  1 m and a seeded yaw), cast without noise; per beam of their voxel-filtered scans the
  hit pushed 0.05 m into the surface is occupied and one point drawn uniformly on
  ``[0, d - 0.3 m]`` (``[0, 80 m)`` for a no-return) is free, every label checked
  against the exact geometry (``Mission3D.truth``), contradicting ones dropped.
- ``sparse``: the same street seen by ``--sparse-scans`` (3) scans of a 16 x 512 lidar,
  2 m apart, labelled the same way.
- ``kitti``: the KITTI-format fixture shipped in ``tests/data/kitti`` (five scans of a
  simulated street, 16 x 24 beams), leave one scan out.
- ``3dtk``: the three real 3DTK scans (``../shared/data/3dtk_example_scans``, skipped
  with a note when absent), leave one scan out.

Leave one scan out: the other scans are mapped; the raw held-out scan gives the test
points (every endpoint occupied, one free point per beam up to 0.1 m short of the hit,
``octolgp.bench.heldout.heldout_points``).

Learning: when a scene has fewer scans than ``learn_scans`` (the sparse case, the
leave-one-out splits) every insert only buffers and ``flush()`` learns; that map is the
one scored, and the scans are then inserted again, alternating with fresh OctoMap and
DUFOMap maps, into a map given the hyperparameters it learnt: those are the "known"
timings of that scene (the table says so).

Deferred fits: by default ``insert_scan`` stores the new evidence and leaves the fits
to the next read (``OnlineConfig.defer_fit``). Each run calls ``OnlineMap.settle()``
after its last insert and times it; the tables give the median insert, that settle, and
the known inserts plus the settle over OctoMap's inserts (summed; the settle counted
whole, also where it fits leaves of the learning insert), which is what a map read once
at the end costs. ``--set online.defer_fit=false`` fits at every insert: what a map read
after every scan costs.

Peers: ``pyoctomap`` (MIT, binding OctoMap, BSD) and ``dufomap`` (BSD, its package
metadata's licence classifier; ``pip install 'octolgp[peers]'``). Either missing
prints a note and leaves its columns empty. DUFOMap runs single-threaded
(``num_threads=1``, ``d_s = 0.2 m``, ``d_p = 1``), as OctoMap does; it is not a map to
score.

Run from the repository root::

    .venv/bin/python tools/bench_3d.py                        # every scene (~15 min, 2 cores)
    .venv/bin/python tools/bench_3d.py --no-exact             # without the exact engine
    .venv/bin/python tools/bench_3d.py --scenes room --scans 6 --hp 0.8
    .venv/bin/python tools/bench_3d.py --quick                # a smoke run of every scene
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import ctypes
import dataclasses
import datetime
import gc
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.bench.dufomap_ref import DufomapReference, dufomap_available
from octolgp.bench.heldout import evaluate, heldout_points
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.scan import Scan
from octolgp.sim.lidar3d import (
    ROOM_SIZE,
    SENSOR_HEIGHT,
    beam_test_points,
    simulate_lidar_room,
    true_labels,
)
from octolgp.sim.mission import Mission3D, simulate_mission3d

ROOT = Path(__file__).resolve().parents[1]
THREEDTK = ROOT.parent / "shared" / "data" / "3dtk_example_scans"
KITTI = ROOT / "tests" / "data" / "kitti" / "sequences" / "00"
RESOLUTION = 0.2
"""Voxel edge of every map and of the voxel-grid filter, metres."""
HP_FIXED = {"signal_variance": 2.0, "noise_variance": 0.01, "alpha": 5.0, "beta": 0.0}
"""The other hyperparameters that go with ``--hp LENGTH_SCALE``."""
SCENES = ("room", "street32", "street64", "sparse", "kitti", "3dtk")
"""Every scene, in the order they run."""
GOAL_RATIO = 1.0
"""Goal: octolgp's median insert at most this times OctoMap's."""
GOAL_VS_EXACT = -0.002
"""Goal: octolgp's AUC minus the exact engine's at least this."""
GOAL_VS_OCTOMAP = 0.003
"""Goal: octolgp's AUC minus OctoMap's at least this."""
STREET_LENGTH = 1000.0
"""Route length of the simulated street world, metres (a 333 x 167 m loop)."""
STREET_START = 100.0
"""Arc length of the first street scan, metres: on the first straight side."""
OCCUPIED_INSIDE = 0.05
"""Held-out hits are pushed this far into the surface, metres."""
FREE_SHORT = 0.3
"""Held-out free points stop this far short of the hit, metres."""


# ----------------------------------------------------------------------------- config
def _parse_value(text: str) -> Any:
    """``--set`` value: a Python literal (``2``, ``0.5``, ``None``, ``True``), else the string."""
    lowered = {"true": True, "false": False, "none": None, "null": None}
    if text.lower() in lowered:
        return lowered[text.lower()]
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def apply_setting(config: MapConfig, setting: str) -> MapConfig:
    """Apply one ``SECTION.FIELD=VALUE`` (or top-level ``FIELD=VALUE``) with ``dataclasses.replace``."""
    key, sep, text = setting.partition("=")
    if not sep or not key:
        raise SystemExit(f"--set {setting!r}: expected SECTION.FIELD=VALUE")
    value = _parse_value(text.strip())
    section, _, name = key.strip().rpartition(".")
    try:
        if not section:
            return dataclasses.replace(config, **{name: value})
        if section not in {f.name for f in dataclasses.fields(config)}:
            raise SystemExit(f"--set {setting!r}: MapConfig has no section {section!r}")
        current: Any = getattr(config, section)
        if current is None:
            raise SystemExit(f"--set {setting!r}: MapConfig.{section} is None (give --hp first)")
        if not dataclasses.is_dataclass(current):
            raise SystemExit(f"--set {setting!r}: MapConfig.{section} is not a section")
        if name not in {f.name for f in dataclasses.fields(current)}:
            names = ", ".join(f.name for f in dataclasses.fields(current))
            raise SystemExit(f"--set {setting!r}: {section} has no field {name!r} ({names})")
        sub: Any = current  # a section dataclass, checked above
        changed: dict[str, Any] = {section: dataclasses.replace(sub, **{name: value})}
        return dataclasses.replace(config, **changed)
    except (TypeError, octolgp.OctolgpError) as exc:
        raise SystemExit(f"--set {setting!r}: {exc}") from None


def _flat(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dataclass fields as ``{"section.field": value}``."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out |= _flat(value, f"{prefix}{f.name}.")
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def non_defaults(config: MapConfig) -> list[str]:
    """``field=value`` for every setting that differs from ``MapConfig(dim=3, resolution=0.2)``."""
    base, mine = _flat(MapConfig(dim=3, resolution=RESOLUTION)), _flat(config)
    changed = [f"{k}={v!r}" for k, v in mine.items() if k not in base or base[k] != v]
    if config.hyperparameters is not None:
        changed = [c for c in changed if not c.startswith("hyperparameters")]
        changed.insert(0, f"hyperparameters={config.hyperparameters} (given, not learnt)")
    return changed


def build_config(args: argparse.Namespace) -> MapConfig:
    """The user default ``MapConfig(dim=3, resolution=0.2)`` changed only by the options."""
    config = MapConfig(dim=3, resolution=RESOLUTION)
    if args.hp is not None:
        config = dataclasses.replace(
            config, hyperparameters=Hyperparameters(length_scale=args.hp, **HP_FIXED)
        )
    if args.learn_scans is not None:
        config = apply_setting(config, f"online.learn_scans={args.learn_scans}")
    for setting in args.set:
        config = apply_setting(config, setting)
    return config


# ----------------------------------------------------------------------------- machine
def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo), else what platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_revision() -> str:
    """The octolgp source's git revision, and the changed package files when it is dirty."""
    source = Path(octolgp.__file__).resolve().parents[1]
    try:
        rev = subprocess.run(
            ["git", "-C", str(source), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        changed = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--", "octolgp"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return f"{source} (not a git checkout)"
    files = [line[3:] for line in changed if line.strip()]
    return f"{source} at {rev}" + (f" (changed: {', '.join(files)})" if files else "")


def rss_mb() -> float:
    """Resident set size now, MB (``/proc/self/statm``; the peak where that is missing)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (``ru_maxrss``, KB on Linux)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


def release_memory() -> None:
    """Collect garbage and hand freed heap back to the system (glibc's ``malloc_trim``).

    A scene's RSS then carries less of the memory the scenes before it freed.
    """
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark of this process (``/proc/self/clear_refs``); False if not."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def peak_rss_since_reset_mb() -> float:
    """Peak RSS since :func:`reset_peak_rss`, MB (``VmHWM``); the lifetime peak where missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 2**10
    except (OSError, ValueError, IndexError):
        pass
    return peak_rss_mb()


# ----------------------------------------------------------------------------- the run
ORDERS = (
    ("octolgp", "octomap", "dufomap"),
    ("octomap", "dufomap", "octolgp"),
    ("dufomap", "octolgp", "octomap"),
)
"""Insertion order of the three maps, rotating with the scan index."""


@dataclass
class PairRun:
    """Per-scan timings of the maps on one scan sequence, and their held-out scores."""

    beams: list[int] = field(default_factory=list)
    octolgp_s: list[float] = field(default_factory=list)
    octomap_s: list[float] = field(default_factory=list)
    refit: list[int] = field(default_factory=list)
    kind: list[str] = field(default_factory=list)  # "buffered", "learning" or "known"
    learn_s: float = float("nan")  # the learning stage inside the learning insert / flush
    flush_s: float | None = None
    flush_refit: int = 0
    scores: dict[str, dict[str, float | int]] = field(default_factory=dict)
    memory_mb: dict[str, float] = field(default_factory=dict)
    eval_s: dict[str, float] = field(default_factory=dict)
    hp: Hyperparameters | None = None
    dufomap_s: list[float] = field(default_factory=list)
    peak_rss_mb: float = float("nan")  # the process, from the first insert to the scoring
    start_rss_mb: float = float("nan")  # the process before the maps were made
    settle_s: float = float("nan")  # OnlineMap.settle() after the last insert (and flush)
    settle_n: int = 0  # the leaves it fitted: those the inserts left pending


def run_pair(
    scans: Sequence[Scan],
    config: MapConfig,
    points: np.ndarray,
    labels: np.ndarray,
    *,
    score: bool = True,
) -> PairRun:
    """Insert ``scans`` into octolgp, OctoMap and DUFOMap alternately, then score octolgp and OctoMap.

    OctoMap and DUFOMap take part when their packages are installed (DUFOMap only in
    3D). With ``score=False`` nothing is scored (a timing-only run).
    """
    out = PairRun()
    release_memory()
    out.start_rss_mb = rss_mb()
    reset_peak_rss()
    m = OnlineMap(config)
    ref = OctomapReference(config.resolution, config.dim) if octomap_available() else None
    duf = None
    if config.dim == 3 and dufomap_available():
        duf = DufomapReference(config.resolution)
    for i, scan in enumerate(scans):
        for who in ORDERS[i % len(ORDERS)]:
            if who == "octomap":
                if ref is not None:
                    t0 = time.perf_counter()
                    ref.insert_scan(scan)
                    out.octomap_s.append(time.perf_counter() - t0)
            elif who == "dufomap":
                if duf is not None:
                    out.dufomap_s.append(duf.insert_scan(scan))
            else:
                t0 = time.perf_counter()
                u = m.insert_scan(scan)
                out.octolgp_s.append(time.perf_counter() - t0)
                out.refit.append(u.refit_leaves)
                if "learning" in u.stages:
                    out.kind.append("learning")
                    out.learn_s = u.stages["learning"]
                else:
                    out.kind.append("buffered" if u.buffered else "known")
        out.beams.append(len(scan))
    if m.buffered_scans:
        t0 = time.perf_counter()
        flushed = m.flush()
        out.flush_s = time.perf_counter() - t0
        if flushed is not None:
            out.flush_refit = flushed.refit_leaves
            out.learn_s = flushed.stages.get("learning", float("nan"))
    t0 = time.perf_counter()
    out.settle_n = m.settle()  # the fits the inserts deferred, before any read
    out.settle_s = time.perf_counter() - t0
    out.hp = m.hyperparameters
    out.memory_mb["octolgp"] = m.memory_bytes() / 2**20
    maps: dict[str, Any] = {"octolgp": m}
    if ref is not None:
        out.memory_mb["OctoMap"] = ref.tree.memoryUsage() / 2**20
        maps["OctoMap"] = ref
    if score:
        for name, obj in maps.items():
            t0 = time.perf_counter()
            out.scores[name] = evaluate(obj, points, labels)
            out.eval_s[name] = time.perf_counter() - t0
    out.peak_rss_mb = peak_rss_since_reset_mb()
    m.close()
    return out


@dataclass
class ExactRun:
    """The exact engine on the same scans, with the same hyperparameters: timed alone, scored."""

    insert_s: list[float] = field(default_factory=list)
    flush_s: float | None = None
    score: dict[str, float | int] | None = None
    eval_s: float = float("nan")
    memory_mb: float = float("nan")


def exact_config(config: MapConfig, hp: Hyperparameters | None) -> MapConfig:
    """``config`` with ``online.engine="exact"`` and the hyperparameters ``hp`` (when given)."""
    online = dataclasses.replace(config.online, engine="exact")
    if hp is None:
        return dataclasses.replace(config, online=online)
    return dataclasses.replace(config, online=online, hyperparameters=hp)


def run_exact(
    scans: Sequence[Scan],
    config: MapConfig,
    hp: Hyperparameters | None,
    points: np.ndarray,
    labels: np.ndarray,
) -> ExactRun:
    """Insert ``scans`` into the exact engine given ``hp``, timing each insert, then score it."""
    out = ExactRun()
    m = OnlineMap(exact_config(config, hp))
    for scan in scans:
        t0 = time.perf_counter()
        m.insert_scan(scan)
        out.insert_s.append(time.perf_counter() - t0)
    if m.buffered_scans:
        t0 = time.perf_counter()
        m.flush()
        out.flush_s = time.perf_counter() - t0
    out.memory_mb = m.memory_bytes() / 2**20
    t0 = time.perf_counter()
    out.score = evaluate(m, points, labels)
    out.eval_s = time.perf_counter() - t0
    m.close()
    return out


@dataclass
class Split:
    """One map to build and score: its (filtered) training scans and labelled test points."""

    label: str
    train: list[Scan]
    points: np.ndarray
    labels: np.ndarray


@dataclass
class Scene:
    """A benchmark scene: a title, what it is, and one split (simulated) or several (leave one out)."""

    key: str
    title: str
    about: list[str]
    splits: list[Split]


@dataclass
class SplitResult:
    """What one split gave: the default run, the timing rerun (if any), the exact engine."""

    split: Split
    run: PairRun
    timing: PairRun | None = None
    exact: ExactRun | None = None

    def timed(self) -> PairRun:
        """The run whose "known" inserts are the scene's timings."""
        return self.timing if self.timing is not None else self.run


def run_split(split: Split, config: MapConfig, with_exact: bool) -> SplitResult:
    """The default run, a timing rerun when every insert only buffered, the exact engine."""
    run = run_pair(split.train, config, split.points, split.labels)
    result = SplitResult(split, run)
    if "known" not in run.kind and run.hp is not None and config.hyperparameters is None:
        given = dataclasses.replace(config, hyperparameters=run.hp)
        result.timing = run_pair(split.train, given, split.points, split.labels, score=False)
    if with_exact:
        hp = config.hyperparameters or run.hp
        result.exact = run_exact(split.train, config, hp, split.points, split.labels)
    return result


# ----------------------------------------------------------------------------- statistics
def _stat(values: Sequence[float], q: float | None = None) -> float:
    if not values:
        return float("nan")
    return float(np.percentile(values, q) if q is not None else np.median(values))


def _fmt(value: float, digits: int = 3) -> str:
    return "–" if value != value else f"{value:.{digits}f}"


def _ratio(a: float, b: float) -> str:
    return "–" if not (a == a and b == b and b > 0) else f"{a / b:.1f}×"


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


@dataclass
class SceneStats:
    """A scene's figures, pooled over its splits."""

    n_known: int
    timing_given: bool  # the known timings come from a rerun given the learnt hyperparameters
    lg: list[float]  # octolgp, known inserts
    om: list[float]  # OctoMap, the same scans
    du: list[float]  # DUFOMap, the same scans
    auc: dict[str, float]
    auc_known: dict[str, float]
    unknown: dict[str, float]
    exact_s: list[float]
    peak_rss: float
    settle: float = 0.0  # seconds of settle() after the timed runs, summed

    @property
    def ratio_total(self) -> float:
        """The known inserts of octolgp plus its settle() over OctoMap's inserts, summed."""
        a, b = sum(self.lg) + self.settle, sum(self.om)
        return a / b if self.om and b > 0 else float("nan")

    @property
    def ratio_octomap(self) -> float:
        """The median known insert of octolgp over OctoMap's, on the same scans."""
        a, b = _stat(self.lg), _stat(self.om)
        return a / b if b == b and b > 0 else float("nan")

    @property
    def ratio_dufomap(self) -> float:
        """The median known insert of octolgp over DUFOMap's, on the same scans."""
        a, b = _stat(self.lg), _stat(self.du)
        return a / b if b == b and b > 0 else float("nan")


def scene_stats(results: Sequence[SplitResult]) -> SceneStats:
    """Pool the splits: known timings concatenated, AUCs averaged, the largest peak RSS."""
    lg: list[float] = []
    om: list[float] = []
    du: list[float] = []
    for r in results:
        t = r.timed()
        known = [i for i, k in enumerate(t.kind) if k == "known"]
        lg += [t.octolgp_s[i] for i in known]
        om += [t.octomap_s[i] for i in known] if t.octomap_s else []
        du += [t.dufomap_s[i] for i in known] if t.dufomap_s else []

    def pooled(key: str) -> dict[str, float]:
        out: dict[str, float] = {}
        for name in ("octolgp", "OctoMap"):
            out[name] = _mean(
                [float(r.run.scores[name][key]) for r in results if name in r.run.scores]
            )
        out["exact"] = _mean(
            [float(r.exact.score[key]) for r in results if r.exact and r.exact.score]
        )
        return out

    peaks = [r.run.peak_rss_mb for r in results] + [
        r.timing.peak_rss_mb for r in results if r.timing is not None
    ]
    return SceneStats(
        n_known=len(lg),
        timing_given=any(r.timing is not None for r in results),
        lg=lg,
        om=om,
        du=du,
        auc=pooled("auc"),
        auc_known=pooled("auc_known"),
        unknown=pooled("unknown_fraction"),
        exact_s=[t for r in results if r.exact for t in r.exact.insert_s],
        peak_rss=max(peaks) if peaks else float("nan"),
        settle=sum(s for r in results if (s := r.timed().settle_s) == s),
    )


def verdict(key: str, stats: SceneStats) -> str:
    """One line: the scene against the three goals."""

    def check(ok: bool | None) -> str:
        return "–" if ok is None else ("**yes**" if ok else "**no**")

    ratio = stats.ratio_octomap
    vs_exact = stats.auc["octolgp"] - stats.auc["exact"]
    vs_om = stats.auc["octolgp"] - stats.auc["OctoMap"]
    parts = [
        f"median insert {_fmt(ratio, 2)}x OctoMap (≤ {GOAL_RATIO:g}x): "
        + check(None if ratio != ratio else ratio <= GOAL_RATIO)
        + f" (inserts + settle {_fmt(stats.ratio_total, 2)}x)",
        f"AUC − exact {'–' if vs_exact != vs_exact else f'{vs_exact:+.4f}'} "
        f"(≥ {GOAL_VS_EXACT:+.3f}): "
        + check(None if vs_exact != vs_exact else vs_exact >= GOAL_VS_EXACT),
        f"AUC − OctoMap {'–' if vs_om != vs_om else f'{vs_om:+.4f}'} "
        f"(≥ {GOAL_VS_OCTOMAP:+.3f}): "
        + check(None if vs_om != vs_om else vs_om >= GOAL_VS_OCTOMAP),
    ]
    return f"Verdict {key}: " + "; ".join(parts) + "."


def goals_met(stats: SceneStats) -> str:
    """How many of the three goals the scene meets, of those it could be checked against."""
    checks = [
        (stats.ratio_octomap, GOAL_RATIO, True),
        (stats.auc["octolgp"] - stats.auc["exact"], GOAL_VS_EXACT, False),
        (stats.auc["octolgp"] - stats.auc["OctoMap"], GOAL_VS_OCTOMAP, False),
    ]
    known = [(v <= g) if le else (v >= g) for v, g, le in checks if v == v]
    return f"{sum(known)}/{len(known)}" if known else "–"


# ----------------------------------------------------------------------------- tables
def summary_table(run: PairRun, results: Sequence[SplitResult] | None = None) -> list[str]:
    """The Markdown summary rows of one scene: ``run`` alone, or every split of ``results``."""
    results = (
        list(results)
        if results is not None
        else [SplitResult(Split("", [], np.empty((0, 3)), np.empty(0)), run)]
    )
    stats = scene_stats(results)
    runs = [r.run for r in results]
    has_octo = any(r.octomap_s for r in runs)
    has_duf = any(r.dufomap_s for r in runs)
    lg_all = [t for r in runs for t in r.octolgp_s]
    om_all = [t for r in runs for t in r.octomap_s]
    du_all = [t for r in runs for t in r.dufomap_s]
    known_what = (
        "given the hyperparameters the default run learnt, every insert"
        if stats.timing_given
        else "learning scan excluded"
    )
    lg, om, du = stats.lg, stats.om, stats.du
    rows = [
        "| measure | octolgp | OctoMap | octolgp / OctoMap | DUFOMap | octolgp / DUFOMap |",
        "|---|---|---|---|---|---|",
        f"| insert s, median, hyperparameters known ({stats.n_known} scans, {known_what}) | "
        f"{_fmt(_stat(lg))} | {_fmt(_stat(om))} (same scans) | {_ratio(_stat(lg), _stat(om))} | "
        f"{_fmt(_stat(du), 4)} | {_ratio(_stat(lg), _stat(du))} |",
        f"| insert s, p90, hyperparameters known | {_fmt(_stat(lg, 90))} | "
        f"{_fmt(_stat(om, 90))} (same scans) | {_ratio(_stat(lg, 90), _stat(om, 90))} | "
        f"{_fmt(_stat(du, 90), 4)} | {_ratio(_stat(lg, 90), _stat(du, 90))} |",
        f"| insert s, median / p90, all {len(lg_all)} inserts of the default run | "
        f"{_fmt(_stat(lg_all))} / {_fmt(_stat(lg_all, 90))} | "
        f"{_fmt(_stat(om_all))} / {_fmt(_stat(om_all, 90))} | – | "
        f"{_fmt(_stat(du_all), 4)} / {_fmt(_stat(du_all, 90), 4)} | – |",
    ]
    buffered = [
        t for r in runs for t, k in zip(r.octolgp_s, r.kind, strict=True) if k == "buffered"
    ]
    if buffered:
        rows.append(
            f"| buffered inserts (learning pending), median s ({len(buffered)} inserts) | "
            f"{_fmt(_stat(buffered), 4)} | – | – | – | – |"
        )
    for r in runs:
        where = f" ({results[runs.index(r)].split.label})" if len(runs) > 1 else ""
        if "learning" in r.kind:
            i = r.kind.index("learning")
            rows.append(
                f"| learning scan {i + 1}{where} s (learn {_fmt(r.learn_s, 2)} s; the step "
                f"changed {r.refit[i]} leaves) | {_fmt(r.octolgp_s[i], 2)} | "
                f"{_fmt(r.octomap_s[i]) if has_octo else '–'} | – | "
                f"{_fmt(r.dufomap_s[i], 4) if has_duf else '–'} | – |"
            )
        if r.flush_s is not None:
            n_buf = sum(k == "buffered" for k in r.kind)
            rows.append(
                f"| flush() after the last scan{where} s (learn {_fmt(r.learn_s, 2)} s, then "
                f"{n_buf} buffered scans: {r.flush_refit} leaves changed, none if stored as they "
                f"came) | {_fmt(r.flush_s, 2)} "
                "| – | – | – | – |"
            )
    settled = [r.settle_s for r in runs if r.settle_s == r.settle_s]
    if settled:
        rows.append(
            f"| settle() after the last insert s (fits the {sum(r.settle_n for r in runs)} "
            f"leaves the inserts left pending{'; summed over the splits' if len(runs) > 1 else ''}"
            f") | {_fmt(sum(settled), 3)} | – | – | – | – |"
        )
    total_lg = sum(lg_all) + sum(r.flush_s or 0.0 for r in runs) + sum(settled)
    total_om = sum(om_all) if has_octo else float("nan")
    total_du = sum(du_all) if has_duf else float("nan")
    rows.append(
        f"| total s, every insert (+ flush, + settle) | {_fmt(total_lg, 2)} | "
        f"{_fmt(total_om, 2)} | {_ratio(total_lg, total_om)} | {_fmt(total_du, 2)} | "
        f"{_ratio(total_lg, total_du)} |"
    )
    if stats.settle:
        rows.append(
            f"| known inserts + settle() of the timed runs, s | "
            f"{_fmt(sum(lg) + stats.settle, 2)} | {_fmt(sum(om), 2)} (same scans) | "
            f"{_ratio(sum(lg) + stats.settle, sum(om))} | – | – |"
        )
    auc_diff = stats.auc["octolgp"] - stats.auc["OctoMap"]
    mean = " (mean of the splits)" if len(runs) > 1 else ""
    rows += [
        f"| held-out AUC (unknown = 0.5){mean} | {_fmt(stats.auc['octolgp'], 4)} | "
        f"{_fmt(stats.auc['OctoMap'], 4)} | "
        f"{'–' if auc_diff != auc_diff else f'{auc_diff:+.4f} (difference)'} | – | – |",
        f"| held-out AUC on the points the map knows | {_fmt(stats.auc_known['octolgp'], 4)} | "
        f"{_fmt(stats.auc_known['OctoMap'], 4)} | – | – | – |",
        f"| unknown fraction of test points | {_fmt(stats.unknown['octolgp'], 4)} | "
        f"{_fmt(stats.unknown['OctoMap'], 4)} | – | – | – |",
    ]
    if any(r.exact for r in results):
        vs = stats.auc["octolgp"] - stats.auc["exact"]
        exact_flush = [r.exact.flush_s for r in results if r.exact and r.exact.flush_s is not None]
        rows += [
            f"| exact engine, same hyperparameters and scans: held-out AUC (unknown fraction) | "
            f"{_fmt(stats.auc['exact'], 4)} ({_fmt(stats.unknown['exact'], 4)}) | – | "
            f"{'–' if vs != vs else f'octolgp − exact {vs:+.4f}'} | – | – |",
            f"| exact engine, insert s median / p90 (timed alone, {len(stats.exact_s)} inserts"
            + (f", + flush {sum(exact_flush):.2f} s" if exact_flush else "")
            + f") | {_fmt(_stat(stats.exact_s), 2)} / {_fmt(_stat(stats.exact_s, 90), 2)} | – | – | – | – |",
        ]
    mem_lg = max(r.memory_mb.get("octolgp", float("nan")) for r in runs)
    mem_om = max(
        (r.memory_mb["OctoMap"] for r in runs if "OctoMap" in r.memory_mb), default=float("nan")
    )
    eval_lg = sum(r.eval_s.get("octolgp", 0.0) for r in runs)
    eval_om = sum(r.eval_s.get("OctoMap", 0.0) for r in runs) if has_octo else float("nan")
    rows += [
        f"| map memory MB (leaves / OcTree::memoryUsage) | {mem_lg:.1f} | {_fmt(mem_om, 1)} | – | – | – |",
        f"| query s for the test points | {eval_lg:.2f} | {_fmt(eval_om, 2)} | – | – | – |",
        f"| peak RSS MB of the process while the maps are alive (VmHWM; "
        f"{_fmt(min(r.start_rss_mb for r in runs), 0)} MB before them) | "
        f"{_fmt(stats.peak_rss, 0)} | – | – | – | – |",
    ]
    return rows


def per_scan_table(run: PairRun) -> list[str]:
    """One Markdown row per inserted scan."""
    rows = [
        "| scan | beams after filter | octolgp s | state | refit leaves | OctoMap s | ratio | DUFOMap s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, beams in enumerate(run.beams):
        om = run.octomap_s[i] if run.octomap_s else float("nan")
        du = run.dufomap_s[i] if run.dufomap_s else float("nan")
        rows.append(
            f"| {i + 1} | {beams} | {run.octolgp_s[i]:.3f} | {run.kind[i]} | {run.refit[i]} | "
            f"{_fmt(om)} | {'–' if run.kind[i] == 'buffered' else _ratio(run.octolgp_s[i], om)} | "
            f"{_fmt(du, 4)} |"
        )
    if run.flush_s is not None:
        rows.append(f"| flush | – | {run.flush_s:.3f} | learning | {run.flush_refit} | – | – | – |")
    return rows


def split_table(results: Sequence[SplitResult]) -> list[str]:
    """One Markdown row per leave-one-out split."""
    rows = [
        "| held out | training scans | test points | octolgp AUC (unknown) | OctoMap AUC (unknown) | "
        "exact AUC (unknown) | octolgp s, known | OctoMap s | DUFOMap s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def cell(score: dict[str, float | int] | None) -> str:
        if score is None:
            return "–"
        return f"{float(score['auc']):.4f} ({float(score['unknown_fraction']):.3f})"

    for r in results:
        t = r.timed()
        known = [i for i, k in enumerate(t.kind) if k == "known"]
        lg = " / ".join(f"{t.octolgp_s[i]:.3f}" for i in known) or "–"
        om = " / ".join(f"{t.octomap_s[i]:.3f}" for i in known if t.octomap_s) or "–"
        du = " / ".join(f"{t.dufomap_s[i]:.4f}" for i in known if t.dufomap_s) or "–"
        rows.append(
            f"| {r.split.label} | {len(r.split.train)} | {r.split.labels.size} | "
            f"{cell(r.run.scores.get('octolgp'))} | {cell(r.run.scores.get('OctoMap'))} | "
            f"{cell(r.exact.score if r.exact else None)} | {lg} | {om} | {du} |"
        )
    return rows


# ----------------------------------------------------------------------------- scenes
def room_scene(args: argparse.Namespace) -> Scene:
    """The simulated room: one split, labelled against the exact boxes."""
    t0 = time.perf_counter()
    room = simulate_lidar_room(
        args.scans,
        seed=args.seed,
        n_azimuth=args.azimuth,
        n_elevation=args.rings,
        max_range=args.max_range,
        range_noise=args.range_noise,
        n_heldout=args.heldout,
    )
    scans = [s.downsample(RESOLUTION) for s in room.scans()]
    points, labels, dropped = room.heldout_points(voxel=RESOLUTION)
    n_raw = room.directions.shape[0]
    title = (
        f"Simulated room: {ROOM_SIZE[0]:g} x {ROOM_SIZE[1]:g} x {ROOM_SIZE[2]:g} m, "
        f"{len(room.boxes)} boxes, {args.rings} x {args.azimuth} lidar at {SENSOR_HEIGHT} m"
    )
    about = [
        f"{len(scans)} scans on an elliptic loop (seed {args.seed}), {n_raw} beams each "
        f"(±15°, {args.max_range:g} m, range noise {args.range_noise:g} m), voxel filter "
        f"{RESOLUTION} m: {_beams(scans)}, the same points to every map. Held out: "
        f"{args.heldout} poses, {labels.size} test points ({int(labels.sum())} occupied, "
        f"{dropped} candidates dropped by the exact-geometry check). Simulated in "
        f"{time.perf_counter() - t0:.1f} s."
    ]
    return Scene("room", title, about, [Split("room", scans, points, labels)])


def _beams(scans: Sequence[Scan]) -> str:
    """``N beams median (lo-hi)`` of the filtered scans."""
    n = [len(s) for s in scans]
    return f"{int(np.median(n))} beams median ({min(n)}-{max(n)})"


def street_heldout_points(
    mission: Mission3D,
    poses: np.ndarray,
    voxel: float | None,
    seed: int,
    inside: float = OCCUPIED_INSIDE,
    short: float = FREE_SHORT,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Labelled test points from held-out street poses, against the exact geometry.

    Per pose ``(x, y, z, yaw)`` a noiseless scan is cast (``Mission3D.cast``); after a
    voxel filter at ``voxel`` (one beam per voxel of its endpoint and kind, so the test
    points spread over the surfaces instead of crowding near the sensor), the hit of
    each returning beam pushed ``inside`` metres further along it is occupied, and one
    point drawn uniformly on ``[0, d - short)`` of a beam of range ``d`` (``[0,
    max_range)`` for a no-return) is free. Every label is checked with
    ``Mission3D.truth`` (inside a box or below the ground); contradicting points (a
    beam grazing a box edge leaves the box within ``inside``) are dropped and counted.

    Returns
    -------
    points : ndarray of shape (m, 3)
        Occupied points first, then free points.
    labels : ndarray of int8, shape (m,)
        1 occupied, 0 free.
    dropped : int
        Candidate points whose label the exact geometry contradicted.
    """
    rng = np.random.default_rng([seed, 2])
    occ, free = [], []
    for pose in np.asarray(poses, dtype=np.float64).reshape(-1, 4):
        scan = mission.cast(pose[:3], float(pose[3]))
        if voxel is not None:
            scan = scan.downsample(voxel)
        delta = scan.points - scan.origin
        t = np.linalg.norm(delta, axis=1)
        keep = t > 1e-9
        t, dirs = t[keep], delta[keep] / t[keep, None]
        hit = t < mission.max_range * (1.0 - 1e-9)
        o, f = beam_test_points(
            scan.origin, t, dirs, hit, mission.max_range, rng, inside=inside, short=short
        )
        occ.append(o)
        free.append(f)
    occupied = np.concatenate(occ) if occ else np.empty((0, 3))
    empty = np.concatenate(free) if free else np.empty((0, 3))
    return true_labels(occupied, empty, mission.truth)


def street_heldout_poses(
    mission: Mission3D, start: float, stretch: float, n: int, seed: int
) -> np.ndarray:
    """``n`` poses ``(x, y, z, yaw)`` spread along ``[start, start + stretch]`` of the route.

    Each sits half-way between two evenly spaced arc lengths, moved sideways by up to
    1 m and turned by a seeded yaw in ``[-pi, pi]``, so its beams differ from every
    training scan's.
    """
    rng = np.random.default_rng([seed, 3])
    s = start + stretch * (np.arange(n) + 0.5) / max(n, 1)
    poses = np.array(mission.route(s), dtype=np.float64).reshape(-1, 4)
    heading = poses[:, 3].copy()
    side = rng.uniform(-1.0, 1.0, n)
    poses[:, 0] -= side * np.sin(heading)
    poses[:, 1] += side * np.cos(heading)
    poses[:, 3] = heading + rng.uniform(-np.pi, np.pi, n)
    return poses


def street_scene(
    key: str,
    args: argparse.Namespace,
    *,
    n_scans: int,
    rings: int,
    azimuth: int,
    fov: tuple[float, float],
    spacing: float,
    n_heldout: int,
) -> Scene:
    """A straight stretch of the simulated street: one split, labelled by ``Mission3D.truth``."""
    t0 = time.perf_counter()
    mission = simulate_mission3d(
        STREET_LENGTH,
        seed=args.seed,
        spacing=spacing,
        n_azimuth=azimuth,
        n_elevation=rings,
        fov_down=fov[0],
        fov_up=fov[1],
        max_range=args.street_range,
        range_noise=args.range_noise,
    )
    first = round(STREET_START / spacing)
    scans = [mission.scan(first + k).downsample(RESOLUTION) for k in range(n_scans)]
    stretch = spacing * max(n_scans - 1, 1)
    poses = street_heldout_poses(mission, first * spacing, stretch, n_heldout, args.seed)
    points, labels, dropped = street_heldout_points(mission, poses, RESOLUTION, args.seed)
    no_return = [
        int(np.sum(np.linalg.norm(s.points - s.origin, axis=1) >= args.street_range * (1 - 1e-9)))
        for s in scans
    ]
    title = (
        f"Simulated street: a {rings} x {azimuth} lidar ({fov[0]:g}°..{fov[1]:g}°), "
        f"ranges to {args.street_range:g} m"
    )
    about = [
        f"`simulate_mission3d({STREET_LENGTH:g}, seed={args.seed})` ({len(mission.boxes)} boxes: "
        f"buildings, fences, poles, trees on a flat ground), lidar {1.0:g} m above the road, "
        f"{n_scans} scans {spacing:g} m apart from {first * spacing:g} m along the route, "
        f"{rings * azimuth} beams each (range noise {args.range_noise:g} m), voxel filter "
        f"{RESOLUTION} m: {_beams(scans)} ({int(np.median(no_return))} no-returns median), "
        f"the same points to every map. Held out: {n_heldout} poses between the training "
        f"poses, {labels.size} test points ({int(labels.sum())} occupied, {dropped} candidates "
        f"dropped by the exact-geometry check). Simulated in {time.perf_counter() - t0:.1f} s."
    ]
    return Scene(key, title, about, [Split(key, scans, points, labels)])


def leave_one_out_scene(
    key: str, title: str, raw: Sequence[Scan], splits: int | None, about: str
) -> Scene:
    """Leave one scan out: per split the other scans (filtered) mapped, the raw one tested."""
    filtered = [s.downsample(RESOLUTION) for s in raw]
    out = []
    for hold in range(len(raw) if splits is None else min(splits, len(raw))):
        pts, labels = heldout_points([raw[hold]], np.random.default_rng(hold), 1, 0.1)
        train = [s for i, s in enumerate(filtered) if i != hold]
        out.append(Split(f"scan {hold}", train, pts, labels))
    lines = [
        f"{about} {len(raw)} scans, {', '.join(str(len(s)) for s in raw)} points, after the "
        f"{RESOLUTION} m filter {', '.join(str(len(s)) for s in filtered)}; {len(out)} splits. "
        "Per split the other scans are mapped (alternating, timed), the raw held-out scan "
        "gives the test points (every endpoint occupied, one free point per beam up to 0.1 m "
        "short of the hit)."
    ]
    return Scene(key, title, lines, out)


def kitti_scene(args: argparse.Namespace) -> Scene | str:
    """The KITTI-format fixture, leave one scan out; a note when it is absent."""
    if not KITTI.is_dir():
        return f"KITTI fixture: skipped, {KITTI} is absent"
    raw = list(load_scans(KITTI))
    return leave_one_out_scene(
        "kitti",
        "KITTI-format fixture (tests/data/kitti), leave one scan out",
        raw,
        args.kitti_splits,
        "A simulated street in the KITTI odometry layout (16 x 24 beams, returns only, "
        "`load_scans`, the Velodyne's world frame, z up):",
    )


def threedtk_scene(args: argparse.Namespace) -> Scene | str:
    """The three real 3DTK scans, leave one scan out; a note when they are absent."""
    if not THREEDTK.is_dir():
        return f"3DTK: skipped, {THREEDTK} is absent (it lives in ../shared/data)"
    raw = list(load_scans(THREEDTK))
    return leave_one_out_scene(
        "3dtk",
        "3DTK scans, leave one scan out",
        raw,
        args.threedtk_splits,
        "Real outdoor scans (3DTK example data, right-handed metric):",
    )


def build_scene(key: str, args: argparse.Namespace) -> Scene | str:
    """The scene ``key`` (one of :data:`SCENES`), or a note saying why it is skipped."""
    if key == "room":
        return room_scene(args)
    if key in ("street32", "street64"):
        rings = 32 if key == "street32" else 64
        fov = (-15.0, 15.0) if rings == 32 else (-24.9, 2.0)
        return street_scene(
            key,
            args,
            n_scans=args.street_scans,
            rings=rings if not args.quick else rings // 4,
            azimuth=args.street_azimuth,
            fov=fov,
            spacing=1.0,
            n_heldout=args.street_heldout,
        )
    if key == "sparse":
        return street_scene(
            key,
            args,
            n_scans=args.sparse_scans,
            rings=args.sparse_rings,
            azimuth=args.sparse_azimuth,
            fov=(-15.0, 15.0),
            spacing=2.0,
            n_heldout=args.street_heldout,
        )
    if key == "kitti":
        return kitti_scene(args)
    if key == "3dtk":
        return threedtk_scene(args)
    raise SystemExit(f"unknown scene {key!r}; choose from {', '.join(SCENES)}")


def short_hp(hp: Hyperparameters | None) -> str:
    """``l, σf², σn², α, β`` of ``hp`` in four significant digits."""
    if hp is None:
        return "none"
    return (
        f"l = {hp.length_scale:.4g} m, σf² = {hp.signal_variance:.4g}, "
        f"σn² = {hp.noise_variance:.4g}, α = {hp.alpha:.4g}, β = {hp.beta:.4g}"
    )


def run_scene(scene: Scene, config: MapConfig, args: argparse.Namespace) -> SceneStats:
    """Run every split of ``scene``, print its tables and verdict, return its figures."""
    print(f"\n## {scene.title}", flush=True)
    for line in scene.about:
        print(line)
    results = []
    for split in scene.splits:
        results.append(run_split(split, config, not args.no_exact))
    hps = [short_hp(r.run.hp) for r in results]
    print(f"octolgp hyperparameters{' per split' if len(hps) > 1 else ''}: {'; '.join(hps)}")
    if not args.no_exact:
        print(
            "Exact engine: the same config with online.engine=exact and these hyperparameters "
            "given, inserted on the same scans after the timed run, timed alone."
        )
    print()
    stats = scene_stats(results)
    print("\n".join(summary_table(results[0].run, results)))
    if len(results) > 1:
        print()
        print("\n".join(split_table(results)))
    if args.per_scan:
        for r in results:
            print()
            if len(results) > 1:
                print(f"Per scan, {r.split.label} held out:")
            print("\n".join(per_scan_table(r.run)))
            if r.timing is not None:
                print()
                print("Per scan, the timing run (hyperparameters given):")
                print("\n".join(per_scan_table(r.timing)))
    print()
    print(verdict(scene.key, stats), flush=True)
    return stats


def final_table(all_stats: dict[str, SceneStats]) -> list[str]:
    """One row per scene: the timings, ratios, AUCs, peak RSS and goals met."""
    rows = [
        "| scene | known inserts | octolgp median s | OctoMap median s | DUFOMap median s | "
        "octolgp / OctoMap | octolgp / DUFOMap | octolgp p90 / OctoMap p90 | "
        "(inserts + settle) / OctoMap | AUC octolgp | "
        "AUC OctoMap | AUC exact | peak RSS MB | goals met |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, s in all_stats.items():
        rows.append(
            f"| {key} | {s.n_known}{' (hp given)' if s.timing_given else ''} | "
            f"{_fmt(_stat(s.lg))} | {_fmt(_stat(s.om))} | {_fmt(_stat(s.du), 4)} | "
            f"{_ratio(_stat(s.lg), _stat(s.om))} | {_ratio(_stat(s.lg), _stat(s.du))} | "
            f"{_ratio(_stat(s.lg, 90), _stat(s.om, 90))} | {_fmt(s.ratio_total, 2)}× | "
            f"{_fmt(s.auc['octolgp'], 4)} | "
            f"{_fmt(s.auc['OctoMap'], 4)} | {_fmt(s.auc['exact'], 4)} | {_fmt(s.peak_rss, 0)} | "
            f"{goals_met(s)} |"
        )
    return rows


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenes",
        default=None,
        help=f"comma-separated scenes to run, from {','.join(SCENES)} (default: all; "
        "--quick: all but 3dtk)",
    )
    parser.add_argument("--scans", type=int, default=None, help="room: training poses (default 12)")
    parser.add_argument("--azimuth", type=int, default=None, help="room: beams per ring (1024)")
    parser.add_argument("--rings", type=int, default=None, help="room: lidar rings (default 32)")
    parser.add_argument("--heldout", type=int, default=None, help="room: held-out poses (3)")
    parser.add_argument("--max-range", type=float, default=30.0, help="room: metres (default 30)")
    parser.add_argument(
        "--street-scans", type=int, default=None, help="street32/64: scans, 1 m apart (default 7)"
    )
    parser.add_argument(
        "--street-azimuth", type=int, default=None, help="street32/64: beams per ring (1024)"
    )
    parser.add_argument(
        "--street-heldout", type=int, default=None, help="street scenes: held-out poses (2)"
    )
    parser.add_argument(
        "--street-range", type=float, default=None, help="street scenes: metres (default 80)"
    )
    parser.add_argument("--sparse-scans", type=int, default=None, help="sparse: scans (default 3)")
    parser.add_argument("--sparse-rings", type=int, default=None, help="sparse: rings (16)")
    parser.add_argument("--sparse-azimuth", type=int, default=None, help="sparse: azimuth (512)")
    parser.add_argument(
        "--kitti-splits", type=int, default=None, help="kitti: first N leave-one-out splits (all)"
    )
    parser.add_argument(
        "--threedtk-splits", type=int, default=None, help="3dtk: first N leave-one-out splits (all)"
    )
    parser.add_argument("--range-noise", type=float, default=0.0, help="metres (default 0)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--hp",
        type=float,
        default=None,
        metavar="LENGTH_SCALE",
        help="give hyperparameters instead of learning: this length scale (m) with "
        + ", ".join(f"{k}={v}" for k, v in HP_FIXED.items()),
    )
    parser.add_argument(
        "--learn-scans",
        type=int,
        default=None,
        metavar="K",
        help="OnlineConfig.learn_scans (default: the config's, 5 in 3D)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="change one MapConfig setting (repeatable), e.g. online.n_jobs=2",
    )
    parser.add_argument("--no-exact", action="store_true", help="skip the exact engine")
    parser.add_argument("--threedtk", action="store_true", help="add 3dtk to the scenes")
    parser.add_argument("--no-sim", action="store_true", help="drop the simulated scenes")
    parser.add_argument("--per-scan", action="store_true", help="print a row per scan")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: tiny sensors, 3 scans a scene, 2 KITTI splits, no 3DTK (under a minute)",
    )
    args = parser.parse_args(argv)
    sizes: dict[str, tuple[Any, Any]] = {  # option: (default, --quick)
        "scans": (12, 2),
        "azimuth": (1024, 128),
        "rings": (32, 8),
        "heldout": (3, 2),
        "street_scans": (7, 2),
        "street_azimuth": (1024, 128),
        "street_heldout": (2, 1),
        "street_range": (80.0, 20.0),
        "sparse_scans": (3, 2),
        "sparse_rings": (16, 4),
        "sparse_azimuth": (512, 64),
        "kitti_splits": (None, 1),
        "threedtk_splits": (None, 1),
    }
    for name, (full, quick) in sizes.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    if args.scenes is None:
        chosen = [s for s in SCENES if not (args.quick and s == "3dtk")]
    else:
        chosen = [s.strip() for s in args.scenes.split(",") if s.strip()]
        bad = [s for s in chosen if s not in SCENES]
        if bad:
            parser.error(f"--scenes: unknown {', '.join(bad)}; choose from {', '.join(SCENES)}")
    if args.threedtk and "3dtk" not in chosen:
        chosen.append("3dtk")
    if args.no_sim:
        chosen = [s for s in chosen if s not in ("room", "street32", "street64", "sparse")]
    args.scene_list = chosen
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its Markdown tables; return the exit status."""
    args = parse_args(argv)
    octomap_available()  # import the peers now, so that they count in the RSS after import
    dufomap_available()
    args.rss_import = peak_rss_mb()
    config = build_config(args)
    words = sys.argv[1:] if argv is None else list(argv)
    print("# Live 3D: octolgp against OctoMap and DUFOMap, 3D lidar at 0.2 m, every scene")
    print(f"Command: `.venv/bin/python tools/bench_3d.py {shlex.join(words)}`".rstrip())
    print(
        f"Machine: {cpu_model()}, {os.cpu_count()} cores ({len(os.sched_getaffinity(0))} usable); "
        f"{platform.system()} {platform.release()}; Python {platform.python_version()}, "
        f"numpy {np.__version__}; octolgp {octolgp.__version__} from {git_revision()}; "
        f"{datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}"
    )
    changes = non_defaults(config)
    print(
        "octolgp: `OnlineMap(MapConfig(dim=3, resolution=0.2))`, the user default, "
        + ("unchanged." if not changes else "with " + "; ".join(changes) + ".")
    )
    print(
        f"Threads: OnlineConfig.n_jobs={config.online.n_jobs} leaf-fitting threads, one BLAS "
        "thread per fit (the map's limit); OctoMap and DUFOMap (num_threads=1) are "
        "single-threaded. Seconds are wall clock (time.perf_counter) around each insert_scan / "
        "insertPointCloud / run call; the three maps take turns scan by scan in one process."
    )
    print(
        f"Goals per scene: median insert ≤ {GOAL_RATIO:g}x OctoMap's; AUC ≥ the exact engine's "
        f"{GOAL_VS_EXACT:+.3f} and ≥ OctoMap's {GOAL_VS_OCTOMAP:+.3f}. Scenes: "
        f"{', '.join(args.scene_list)}."
    )
    if not octomap_available():
        print("OctoMap: pyoctomap is not installed; its columns are empty (pip install pyoctomap).")
    if not dufomap_available():
        print("DUFOMap: dufomap is not installed; its columns are empty (pip install dufomap).")
    t_start = time.perf_counter()
    all_stats: dict[str, SceneStats] = {}
    notes: list[str] = []
    for key in args.scene_list:
        scene = build_scene(key, args)
        if isinstance(scene, str):
            print(f"\n## {scene}")
            notes.append(scene)
            continue
        all_stats[key] = run_scene(scene, config, args)
    print("\n## Every scene")
    print()
    print("\n".join(final_table(all_stats)))
    print()
    for key, stats in all_stats.items():
        print(verdict(key, stats))
    for note in notes:
        print(f"Not run: {note}.")
    peak = max(
        [peak_rss_mb(), *(s.peak_rss for s in all_stats.values() if s.peak_rss == s.peak_rss)]
    )
    print(
        f"\nProcess RSS after import {args.rss_import:.0f} MB; peak over the run {peak:.0f} MB "
        "(each scene's peak is measured from a reset of the kernel's mark, "
        f"/proc/self/clear_refs). Wall time {time.perf_counter() - t_start:.0f} s."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
