"""Per-scan ``insert_scan`` time of the 2D online map as a new user gets it.

Figures: BENCHMARKS.md, "2D: Intel, per-scan time as a new user gets it".

``OnlineMap(MapConfig(dim=2, resolution=0.1))`` with nothing else set: the first
``learn_scans`` (40) scans are buffered, the hyperparameters are learnt on them at the
40th, then every scan is inserted. Prints the median and p90 of every insert over the
first ``--scans`` scans (buffered ones included, as a user's loop sees them), of the
inserts after learning, and the learning scan, for each ``--set`` variant given
(``SECTION.FIELD=VALUE``, several per variant separated by ``;``), default first.

Run from the repository root (the Intel log ships with the repository)::

    .venv/bin/python tools/bench_2d_online.py
    .venv/bin/python tools/bench_2d_online.py --variant "online.engine=exact"
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from octolgp import MapConfig, OnlineMap, load_scans

REPO = Path(__file__).resolve().parent.parent
INTEL = REPO / "data" / "intel_lab" / "intel-corrected.log.gz"


def parse(value: str) -> object:
    """A ``--set`` value: int, float, bool or string."""
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return {"True": True, "False": False}.get(value, value)


def config_of(variant: str) -> MapConfig:
    """``MapConfig(dim=2, resolution=0.1)`` with the variant's settings."""
    config = MapConfig(dim=2, resolution=0.1)
    for item in filter(None, (s.strip() for s in variant.split(";"))):
        name, value = item.split("=", 1)
        section, field = name.split(".", 1)
        part = dataclasses.replace(getattr(config, section), **{field: parse(value)})
        config = dataclasses.replace(config, **{section: part})
    return config


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", type=Path, default=INTEL, help="CARMEN log (default: Intel)")
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--variant", action="append", default=[], help="settings, ';'-separated")
    args = parser.parse_args()
    scans = list(load_scans(args.log))[: args.scans]
    cpu = platform.processor() or platform.machine()
    print(f"`{' '.join(['tools/bench_2d_online.py', *sys.argv[1:]])}`")
    print(f"Machine: {cpu}, {os.cpu_count()} cores; log {args.log.name}, first {len(scans)} scans")
    print()
    print(
        "| config | median ms (all) | p90 ms (all) | median ms (after learning) | "
        "p90 ms (after learning) | learning scan s | leaves |"
    )
    print("|---|---|---|---|---|---|---|")
    for variant in ["", *args.variant]:
        m = OnlineMap(config_of(variant))
        seconds, buffered = [], []
        for s in scans:
            t = time.perf_counter()
            u = m.insert_scan(s)
            seconds.append(time.perf_counter() - t)
            buffered.append(u.buffered or "learning" in u.stages)
        sec = np.array(seconds) * 1e3
        after = sec[~np.array(buffered)]
        learn = [x for x, b, u in zip(sec, buffered, seconds, strict=True) if b and x > 100]
        print(
            f"| {variant or 'default'} | {np.median(sec):.1f} | {np.percentile(sec, 90):.1f} | "
            f"{np.median(after):.1f} | {np.percentile(after, 90):.1f} | "
            f"{(learn[0] / 1e3 if learn else float('nan')):.1f} | {len(m.store)} |",
            flush=True,
        )
        m.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
