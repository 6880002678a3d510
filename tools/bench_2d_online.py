"""Per-scan ``insert_scan`` time of the 2D online map as a new user gets it, against OctoMap.

Figures: BENCHMARKS.md, "2D: Intel, per-scan time as a new user gets it".

``OnlineMap(MapConfig(dim=2, resolution=0.1))`` with nothing else set: the first
``learn_scans`` (40) scans are buffered, the hyperparameters are learnt on them at the
40th, then every scan is inserted. OctoMap (``pyoctomap`` through
:class:`octolgp.bench.octomap_ref.OctomapReference`: the 2D scan lifted to ``z =
resolution / 2``, no-return beams free to ``max_range`` and no hit) maps the same scans in
the same process, the two inserted alternately scan by scan (the order swaps every
scan), each call timed with ``time.perf_counter``.

Printed per log and per ``--set`` variant (``SECTION.FIELD=VALUE``, several per variant
separated by ``;``; the default first): the median and p90 of every insert over the
first ``--scans`` scans (buffered ones included, as a user's loop sees them); the
median, p90 and p99 of the inserts after learning and p99 / median; OctoMap's median
and p90 over the same scans and the ratio octolgp / OctoMap; the learning step (the
insert at scan ``learn_scans``, and its ``stages["learning"]``); the ``settle()`` after
the last insert (the fits the inserts deferred, ``OnlineConfig.defer_fit``) and the sum
of the inserts after learning plus that settle over OctoMap's sum, which is what a map
read once at the end costs (``--variant online.defer_fit=false``: fitted at every insert,
what a map read after every scan costs). A verdict line checks the goal on the default:
median after learning at most 0.5x OctoMap's in the same run.

Logs: Intel (ships with the repository), ``--fr079`` adds Freiburg 079
(``../shared/data/fr079``, skipped with a note when absent), ``--log`` maps another
CARMEN log instead of Intel.

Run from the repository root::

    .venv/bin/python tools/bench_2d_online.py
    .venv/bin/python tools/bench_2d_online.py --fr079
    .venv/bin/python tools/bench_2d_online.py --variant "online.engine=exact"
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from bench_3d import cpu_model, git_revision, peak_rss_mb

import octolgp
from octolgp import MapConfig, OnlineMap, load_scans
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.scan import Scan

REPO = Path(__file__).resolve().parent.parent
INTEL = REPO / "data" / "intel_lab" / "intel-corrected.log.gz"
FR079 = REPO.parent / "shared" / "data" / "fr079" / "freiburg-079-corrected.log.gz"
RESOLUTION = 0.1
"""Cell edge of both maps, metres."""
GOAL_RATIO = 0.5
"""Goal: octolgp's median insert after learning at most this times OctoMap's."""


def parse(value: str) -> object:
    """A ``--set`` value: int, float, bool or string."""
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(value.lower(), value)


def config_of(variant: str) -> MapConfig:
    """``MapConfig(dim=2, resolution=0.1)`` with the variant's settings."""
    config = MapConfig(dim=2, resolution=RESOLUTION)
    for item in filter(None, (s.strip() for s in variant.split(";"))):
        name, value = item.split("=", 1)
        section, field_name = name.split(".", 1)
        part = dataclasses.replace(getattr(config, section), **{field_name: parse(value)})
        config = dataclasses.replace(config, **{section: part})
    return config


@dataclass
class Run2D:
    """Per-scan timings of octolgp and OctoMap on one log, one variant."""

    octolgp_s: list[float] = field(default_factory=list)
    octomap_s: list[float] = field(default_factory=list)
    kind: list[str] = field(default_factory=list)  # "buffered", "learning" or "known"
    learn_s: float = float("nan")  # stages["learning"] of the learning insert
    flush_s: float | None = None
    leaves: int = 0
    settle_s: float = 0.0  # OnlineMap.settle() after the last insert: the deferred fits

    def after(self) -> tuple[list[float], list[float]]:
        """The seconds of octolgp and of OctoMap over the inserts after learning."""
        known = [i for i, k in enumerate(self.kind) if k == "known"]
        om = [self.octomap_s[i] for i in known] if self.octomap_s else []
        return [self.octolgp_s[i] for i in known], om


def run_log(scans: Sequence[Scan], config: MapConfig) -> Run2D:
    """Insert ``scans`` into octolgp and (when installed) OctoMap alternately, timing each call."""
    out = Run2D()
    m = OnlineMap(config)
    ref = OctomapReference(config.resolution, 2) if octomap_available() else None
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
            if "learning" in u.stages:
                out.kind.append("learning")
                out.learn_s = u.stages["learning"]
            else:
                out.kind.append("buffered" if u.buffered else "known")
    if m.buffered_scans:
        t0 = time.perf_counter()
        flushed = m.flush()
        out.flush_s = time.perf_counter() - t0
        if flushed is not None:
            out.learn_s = flushed.stages.get("learning", float("nan"))
    t0 = time.perf_counter()
    m.settle()
    out.settle_s = time.perf_counter() - t0
    out.leaves = len(m.store)
    m.close()
    return out


def _ms(values: Sequence[float], q: float | None = None) -> float:
    """Median (or percentile ``q``) of seconds, in milliseconds; NaN for none."""
    if not values:
        return float("nan")
    return 1e3 * float(np.median(values) if q is None else np.percentile(values, q))


def _f(value: float, digits: int = 1) -> str:
    return "–" if value != value else f"{value:.{digits}f}"


def _ratio(a: float, b: float, digits: int = 2) -> str:
    return "–" if not (a == a and b == b and b > 0) else f"{a / b:.{digits}f}×"


def timing_row(name: str, run: Run2D) -> str:
    """The octolgp row: every insert, after learning, the learning step."""
    after, _ = run.after()
    learning = [i for i, k in enumerate(run.kind) if k == "learning"]
    if learning:
        i = learning[0]
        step = f"{run.octolgp_s[i]:.2f} (scan {i + 1}) | {_f(run.learn_s, 2)}"
    elif run.flush_s is not None:
        step = f"{run.flush_s:.2f} (flush) | {_f(run.learn_s, 2)}"
    else:
        step = "– | –"
    p99, med = _ms(after, 99), _ms(after)
    return (
        f"| {name} | {_f(_ms(run.octolgp_s))} | {_f(_ms(run.octolgp_s, 90))} | {len(after)} | "
        f"{_f(med)} | {_f(_ms(after, 90))} | {_f(p99)} | {_ratio(p99, med, 1)} | {step} | "
        f"{run.leaves} |"
    )


def octomap_row(name: str, run: Run2D) -> str:
    """The comparison row: both maps over the inserts after learning."""
    lg, om = run.after()
    total = _ratio(sum(lg) + run.settle_s, sum(om)) if om else "–"
    return (
        f"| {name} | {_f(_ms(lg))} | {_f(_ms(om), 2)} | {_ratio(_ms(lg), _ms(om))} | "
        f"{_f(_ms(lg, 90))} | {_f(_ms(om, 90), 2)} | {_ratio(_ms(lg, 90), _ms(om, 90))} | "
        f"{_f(run.settle_s, 3)} | {total} | {_f(_ms(run.octomap_s), 2)} |"
    )


def verdict(log: str, run: Run2D) -> str:
    """One line: the default's median after learning against the goal."""
    lg, om = run.after()
    a, b = _ms(lg), _ms(om)
    if not (a == a and b == b and b > 0):
        return f"Verdict {log}: – (no OctoMap timings or no inserts after learning)."
    ok = a / b <= GOAL_RATIO
    return (
        f"Verdict {log}: median insert after learning {a:.1f} ms = {a / b:.2f}x OctoMap's "
        f"{b:.2f} ms (goal ≤ {GOAL_RATIO:g}x): {'**yes**' if ok else '**no**'}."
    )


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", type=Path, default=INTEL, help="CARMEN log (default: Intel)")
    parser.add_argument("--fr079", action="store_true", help="also map Freiburg 079")
    parser.add_argument("--scans", type=int, default=300, help="first N scans of each log")
    parser.add_argument(
        "--learn-scans",
        type=int,
        default=None,
        metavar="K",
        help="OnlineConfig.learn_scans for every variant (default: the config's, 40 in 2D)",
    )
    parser.add_argument("--variant", action="append", default=[], help="settings, ';'-separated")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its Markdown tables; return the exit status."""
    args = parse_args(argv)
    words = sys.argv[1:] if argv is None else list(argv)
    print("# 2D online: octolgp's insert_scan against OctoMap, 0.1 m, as a new user gets it")
    print(f"Command: `.venv/bin/python tools/bench_2d_online.py {shlex.join(words)}`".rstrip())
    print(
        f"Machine: {cpu_model()}, {os.cpu_count()} cores ({len(os.sched_getaffinity(0))} usable); "
        f"{platform.system()} {platform.release()}; Python {platform.python_version()}, "
        f"numpy {np.__version__}; octolgp {octolgp.__version__} from {git_revision()}; "
        f"{datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}"
    )
    print(
        "octolgp: `OnlineMap(MapConfig(dim=2, resolution=0.1))`, the user default, and the "
        "variants; OctoMap: `OcTree(0.1)` through OctomapReference, the scan lifted to "
        "z = 0.05 m. The two take turns scan by scan in one process; seconds are wall clock "
        "(time.perf_counter) around each insert_scan / insertPointCloud call."
    )
    if not octomap_available():
        print("OctoMap: pyoctomap is not installed; its columns are empty (pip install pyoctomap).")
    logs = [args.log]
    if args.fr079:
        if FR079.is_file():
            logs.append(FR079)
        else:
            print(f"FR079: skipped, {FR079} is absent (it lives in ../shared/data/fr079).")
    verdicts = []
    variants = ["", *args.variant]
    for log in logs:
        scans = list(load_scans(log))[: args.scans]
        print(f"\n## {log.name}: first {len(scans)} scans")
        runs = []
        for variant in variants:
            settings = variant
            if args.learn_scans is not None:
                settings = f"online.learn_scans={args.learn_scans};{variant}"
            runs.append((variant or "default", run_log(scans, config_of(settings))))
        print()
        print(
            "| config | median ms (all) | p90 ms (all) | inserts after learning | median ms "
            "(after learning) | p90 ms (after learning) | p99 ms (after learning) | p99 / median | "
            "learning step s (the insert) | of which learning s | leaves |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for name, run in runs:
            print(timing_row(name, run))
        print()
        print(
            "| config | octolgp median ms (after learning) | OctoMap median ms (same scans) | "
            "octolgp / OctoMap | octolgp p90 ms | OctoMap p90 ms | p90 ratio | "
            "settle() s (once, at the end) | (inserts after learning + settle) / OctoMap, "
            "summed | OctoMap median ms (all scans) |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        for name, run in runs:
            print(octomap_row(name, run))
        print()
        verdicts.append(verdict(log.name.split("-")[0], runs[0][1]))
        print(verdicts[-1], flush=True)
    print(f"\nPeak RSS {peak_rss_mb():.0f} MB (ru_maxrss).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
