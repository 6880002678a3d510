"""Real-time 3D benchmark: octolgp and the real OctoMap on the same 3D lidar scans.

Figures: BENCHMARKS.md, "3D: a 32 x 1024 lidar in a room, against the real OctoMap".

Simulation (``octolgp.sim.lidar3d.simulate_lidar_room``): a 20 x 20 x 5 m room of
axis-aligned boxes (walls, floor, ceiling and 14 pillars, crates, shelves, a duct ...),
a 32 x 1024 lidar (360° azimuth, rings -15°..+15°, 30 m range, no range noise by
default) 1.2 m above the floor at ``--scans`` poses around an elliptic loop, each
with a seeded yaw. Every scan goes through ``Scan.downsample(0.2)`` and the same
filtered points go to both maps, inserted alternately scan by scan in one process,
each ``insert_scan`` timed with ``time.perf_counter``. octolgp is
``OnlineMap(MapConfig(dim=3, resolution=0.2))``, the configuration a user gets,
changed only by the options below (the header lists every change).

Held-out accuracy against the exact geometry: ``--heldout`` extra poses, never
inserted; per beam of their voxel-filtered scans the hit pushed 0.05 m into the
surface is occupied and one point drawn uniformly on ``[0, d - 0.3 m]`` is free,
each label checked against the exact box geometry. AUC with unknown points at 0.5
(``octolgp.bench.heldout.evaluate``), and the fraction of test points each map leaves
unknown.

Learning: with no ``--hp`` the map learns its hyperparameters once
``MapConfig.learn_scans`` scans are buffered (default 5 in 3D; ``--learn-scans``
changes it); until then inserts only buffer. That scan's insert (learning plus
fitting every buffered scan) is reported on its own row, and if the run ends before
it, ``flush()`` is called after the last insert and timed as its own row. Medians
and p90s "after hyperparameters are known" exclude the buffered inserts and the
learning scan.

``--threedtk`` adds the same comparison on the three real 3DTK scans
(``../shared/data/3dtk_example_scans``, skipped with a note when absent), leave
one scan out: map two voxel-filtered scans, test on every endpoint of the raw third
(occupied) and one free point per beam up to 0.1 m short of the hit, as
``octolgp eval --leave-one-out`` does.

Run from the repository root::

    .venv/bin/python tools/bench_3d.py                       # 24 scans, learnt hyperparameters
    .venv/bin/python tools/bench_3d.py --scans 6 --hp 0.8    # given hyperparameters
    .venv/bin/python tools/bench_3d.py --learn-scans 4 --set online.n_jobs=2 --threedtk
    .venv/bin/python tools/bench_3d.py --quick --hp 0.8      # a tiny smoke run (8 x 128 lidar)
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import datetime
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
from octolgp.bench.heldout import evaluate, heldout_points
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.scan import Scan
from octolgp.sim.lidar3d import ROOM_SIZE, SENSOR_HEIGHT, simulate_lidar_room

ROOT = Path(__file__).resolve().parents[1]
THREEDTK = ROOT.parent / "shared" / "data" / "3dtk_example_scans"
RESOLUTION = 0.2
"""Voxel edge of both maps and of the voxel-grid filter, metres."""
HP_FIXED = {"signal_variance": 2.0, "noise_variance": 0.01, "alpha": 5.0, "beta": 0.0}
"""The other hyperparameters that go with ``--hp LENGTH_SCALE``."""


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


# ----------------------------------------------------------------------------- the run
@dataclass
class PairRun:
    """Per-scan timings of both maps on one scan sequence, and their held-out scores."""

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


def run_pair(
    scans: Sequence[Scan], config: MapConfig, points: np.ndarray, labels: np.ndarray
) -> PairRun:
    """Insert ``scans`` into octolgp and OctoMap alternately, then score both on the test points."""
    out = PairRun()
    m = OnlineMap(config)
    ref = OctomapReference(config.resolution, 3) if octomap_available() else None
    for i, scan in enumerate(scans):
        for who in ("octolgp", "octomap") if i % 2 == 0 else ("octomap", "octolgp"):
            if who == "octomap":
                if ref is not None:
                    t0 = time.perf_counter()
                    ref.insert_scan(scan)
                    out.octomap_s.append(time.perf_counter() - t0)
                continue
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
    out.hp = m.hyperparameters
    out.memory_mb["octolgp"] = m.memory_bytes() / 2**20
    maps: dict[str, Any] = {"octolgp": m}
    if ref is not None:
        out.memory_mb["OctoMap"] = ref.tree.memoryUsage() / 2**20
        maps["OctoMap"] = ref
    for name, obj in maps.items():
        t0 = time.perf_counter()
        out.scores[name] = evaluate(obj, points, labels)
        out.eval_s[name] = time.perf_counter() - t0
    m.close()
    return out


def _stat(values: Sequence[float], q: float | None = None) -> float:
    if not values:
        return float("nan")
    return float(np.percentile(values, q) if q is not None else np.median(values))


def _fmt(value: float, digits: int = 3) -> str:
    return "–" if value != value else f"{value:.{digits}f}"


def _ratio(a: float, b: float) -> str:
    return "–" if not (a == a and b == b and b > 0) else f"{a / b:.1f}×"


def summary_table(run: PairRun) -> list[str]:
    """The Markdown summary rows of one :class:`PairRun`."""
    has_octo = bool(run.octomap_s)
    known = [i for i, k in enumerate(run.kind) if k == "known"]
    buffered = [i for i, k in enumerate(run.kind) if k == "buffered"]
    learning = [i for i, k in enumerate(run.kind) if k == "learning"]
    lg = [run.octolgp_s[i] for i in known]
    om_known = [run.octomap_s[i] for i in known] if has_octo else []
    om_all = run.octomap_s
    rows = [
        "| measure | octolgp | OctoMap | octolgp / OctoMap |",
        "|---|---|---|---|",
        f"| insert s, median, hyperparameters known ({len(known)} scans, learning scan excluded) | "
        f"{_fmt(_stat(lg))} | {_fmt(_stat(om_known))} (same scans) | "
        f"{_ratio(_stat(lg), _stat(om_known))} |",
        f"| insert s, p90, hyperparameters known | {_fmt(_stat(lg, 90))} | "
        f"{_fmt(_stat(om_known, 90))} (same scans) | {_ratio(_stat(lg, 90), _stat(om_known, 90))} |",
        f"| insert s, median / p90, all {len(run.beams)} scans | "
        f"{_fmt(_stat(run.octolgp_s))} / {_fmt(_stat(run.octolgp_s, 90))} | "
        f"{_fmt(_stat(om_all))} / {_fmt(_stat(om_all, 90))} | – |",
    ]
    if buffered:
        b = [run.octolgp_s[i] for i in buffered]
        rows.append(
            f"| buffered inserts (learning pending), median s ({len(buffered)} scans) | "
            f"{_fmt(_stat(b), 4)} | – | – |"
        )
    if learning:
        i = learning[0]
        rows.append(
            f"| learning scan {i + 1} s (learn {_fmt(run.learn_s, 2)} s, then fit {i + 1} "
            f"scans, {run.refit[i]} leaves) | {_fmt(run.octolgp_s[i], 2)} | "
            f"{_fmt(run.octomap_s[i]) if has_octo else '–'} | – |"
        )
    if run.flush_s is not None:
        rows.append(
            f"| flush() after the last scan s (learn {_fmt(run.learn_s, 2)} s, then fit "
            f"{len(buffered)} buffered scans, {run.flush_refit} leaves) | {_fmt(run.flush_s, 2)} "
            "| – | – |"
        )
    total_lg = sum(run.octolgp_s) + (run.flush_s or 0.0)
    total_om = sum(om_all) if has_octo else float("nan")
    rows.append(
        f"| total s, every insert (+ flush) | {_fmt(total_lg, 2)} | {_fmt(total_om, 2)} | "
        f"{_ratio(total_lg, total_om)} |"
    )

    def score(name: str, key: str) -> float:
        s = run.scores.get(name)
        return float("nan") if s is None else float(s[key])

    auc_diff = score("octolgp", "auc") - score("OctoMap", "auc")
    rows += [
        f"| held-out AUC (unknown = 0.5) | {_fmt(score('octolgp', 'auc'), 4)} | "
        f"{_fmt(score('OctoMap', 'auc'), 4)} | "
        f"{'–' if auc_diff != auc_diff else f'{auc_diff:+.4f} (difference)'} |",
        f"| held-out AUC on the points the map knows | {_fmt(score('octolgp', 'auc_known'), 4)} | "
        f"{_fmt(score('OctoMap', 'auc_known'), 4)} | – |",
        f"| unknown fraction of test points | {_fmt(score('octolgp', 'unknown_fraction'), 4)} | "
        f"{_fmt(score('OctoMap', 'unknown_fraction'), 4)} | – |",
        f"| map memory MB (leaves / OcTree::memoryUsage) | {run.memory_mb['octolgp']:.1f} | "
        f"{_fmt(run.memory_mb.get('OctoMap', float('nan')), 1)} | – |",
        f"| query s for the test points | {run.eval_s['octolgp']:.2f} | "
        f"{_fmt(run.eval_s.get('OctoMap', float('nan')), 2)} | – |",
    ]
    return rows


def per_scan_table(run: PairRun) -> list[str]:
    """One Markdown row per inserted scan."""
    rows = [
        "| scan | beams after filter | octolgp s | state | refit leaves | OctoMap s | ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for i, beams in enumerate(run.beams):
        om = run.octomap_s[i] if run.octomap_s else float("nan")
        rows.append(
            f"| {i + 1} | {beams} | {run.octolgp_s[i]:.3f} | {run.kind[i]} | {run.refit[i]} | "
            f"{_fmt(om)} | {'–' if run.kind[i] == 'buffered' else _ratio(run.octolgp_s[i], om)} |"
        )
    if run.flush_s is not None:
        rows.append(f"| flush | – | {run.flush_s:.3f} | learning | {run.flush_refit} | – | – |")
    return rows


def part_sim(args: argparse.Namespace, config: MapConfig) -> None:
    """The simulated room: both maps, alternating, scored against the exact geometry."""
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
    t_sim = time.perf_counter() - t0
    rss_sim = rss_mb()
    n_raw = room.directions.shape[0]
    print(
        f"\n## Simulated room: {ROOM_SIZE[0]:g} x {ROOM_SIZE[1]:g} x {ROOM_SIZE[2]:g} m, "
        f"{len(room.boxes)} boxes, {args.rings} x {args.azimuth} lidar at {SENSOR_HEIGHT} m"
    )
    print(
        f"{len(scans)} scans on an elliptic loop (seed {args.seed}), {n_raw} beams each "
        f"(±15°, {args.max_range:g} m, range noise {args.range_noise:g} m), voxel filter "
        f"{RESOLUTION} m: {int(np.median([len(s) for s in scans]))} beams median "
        f"({min(len(s) for s in scans)}-{max(len(s) for s in scans)}), the same points to both maps. "
        f"Held out: {args.heldout} poses, {labels.size} test points ({int(labels.sum())} occupied, "
        f"{dropped} candidates dropped by the exact-geometry check). Simulated in {t_sim:.1f} s."
    )
    run = run_pair(scans, config, points, labels)
    peak = peak_rss_mb()
    print(f"octolgp hyperparameters: {run.hp}")
    print()
    print("\n".join(summary_table(run)))
    print(
        f"\nProcess RSS (both maps in one process): {args.rss_import:.0f} MB after import, "
        f"{rss_sim:.0f} MB with the scans simulated, peak {peak:.0f} MB (ru_maxrss)."
    )
    if args.per_scan:
        print()
        print("\n".join(per_scan_table(run)))


def part_threedtk(config: MapConfig) -> None:
    """3DTK: leave one scan out, two voxel-filtered scans mapped, the raw third tested."""
    if not THREEDTK.is_dir():
        print(f"\n## 3DTK: skipped, {THREEDTK} is absent (it lives in ../shared/data)")
        return
    raw: list[Scan] = list(load_scans(THREEDTK))
    filtered = [s.downsample(RESOLUTION) for s in raw]
    print(
        f"\n## 3DTK scans, leave one scan out: {len(raw)} scans, "
        f"{', '.join(str(len(s)) for s in raw)} points, after the {RESOLUTION} m filter "
        f"{', '.join(str(len(s)) for s in filtered)}"
    )
    print(
        "Per split: the other scans inserted alternately into both maps (timed), test points "
        "from the raw held-out scan (every endpoint occupied, one free point per beam up to "
        "0.1 m short of the hit)."
    )
    print()
    print(
        "| held out | test points | octolgp s per insert | flush s | OctoMap s per insert | "
        "octolgp AUC (unknown) | OctoMap AUC (unknown) |"
    )
    print("|---|---|---|---|---|---|---|")
    lg_known: list[float] = []
    om_all: list[float] = []
    aucs: dict[str, list[float]] = {"octolgp": [], "OctoMap": []}
    for hold in range(len(raw)):
        pts, labels = heldout_points([raw[hold]], np.random.default_rng(hold), 1, 0.1)
        train = [s for i, s in enumerate(filtered) if i != hold]
        run = run_pair(train, config, pts, labels)
        lg_known += [t for t, k in zip(run.octolgp_s, run.kind, strict=True) if k == "known"]
        om_all += run.octomap_s
        cells = {}
        for name in ("octolgp", "OctoMap"):
            s = run.scores.get(name)
            cells[name] = (
                "–" if s is None else f"{float(s['auc']):.4f} ({float(s['unknown_fraction']):.3f})"
            )
            if s is not None:
                aucs[name].append(float(s["auc"]))
        print(
            f"| scan {hold} | {labels.size} | "
            + " / ".join(
                f"{t:.2f}{'' if k == 'known' else ' ' + k}"
                for t, k in zip(run.octolgp_s, run.kind, strict=True)
            )
            + f" | {'–' if run.flush_s is None else f'{run.flush_s:.2f}'} | "
            + (" / ".join(f"{t:.3f}" for t in run.octomap_s) or "–")
            + f" | {cells['octolgp']} | {cells['OctoMap']} |"
        )
    mean = {k: f"{np.mean(v):.4f}" if v else "–" for k, v in aucs.items()}
    print(
        f"| mean | | median {_fmt(_stat(lg_known), 2)} (hyperparameters known) | | "
        f"median {_fmt(_stat(om_all))} | {mean['octolgp']} | {mean['OctoMap']} |"
    )
    print(
        f"octolgp / OctoMap, median insert with hyperparameters known: "
        f"{_ratio(_stat(lg_known), _stat(om_all))}; peak RSS so far {peak_rss_mb():.0f} MB."
    )


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=None, help="training poses (default 24)")
    parser.add_argument("--azimuth", type=int, default=None, help="beams per ring (default 1024)")
    parser.add_argument("--rings", type=int, default=None, help="lidar rings (default 32)")
    parser.add_argument("--heldout", type=int, default=None, help="held-out poses (default 3)")
    parser.add_argument("--max-range", type=float, default=30.0, help="metres (default 30)")
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
    parser.add_argument("--threedtk", action="store_true", help="also run the 3DTK scans")
    parser.add_argument("--no-sim", action="store_true", help="skip the simulated room")
    parser.add_argument("--per-scan", action="store_true", help="print a row per scan")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a tiny smoke run: 3 scans of an 8 x 128 lidar, 2 held out (about 10 s with --hp)",
    )
    args = parser.parse_args(argv)
    defaults = (3, 128, 8, 2) if args.quick else (24, 1024, 32, 3)
    for name, value in zip(("scans", "azimuth", "rings", "heldout"), defaults, strict=True):
        if getattr(args, name) is None:
            setattr(args, name, value)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its Markdown tables; return the exit status."""
    args = parse_args(argv)
    octomap_available()  # import pyoctomap now, so that it counts in the RSS after import
    args.rss_import = peak_rss_mb()
    config = build_config(args)
    words = sys.argv[1:] if argv is None else list(argv)
    print("# octolgp vs OctoMap, 3D lidar at 0.2 m (issue #14)")
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
        "thread per fit (the map's limit); OctoMap is single-threaded. Seconds are wall clock "
        "(time.perf_counter) around each insert_scan / insertPointCloud call."
    )
    if not octomap_available():
        print("OctoMap: pyoctomap is not installed; its columns are empty (pip install pyoctomap).")
    if not args.no_sim:
        part_sim(args, config)
    if args.threedtk:
        part_threedtk(config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
