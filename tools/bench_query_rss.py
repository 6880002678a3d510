"""The RSS a large query adds: ``occupancy`` at 10^7 points of a 2D map.

Figures: BENCHMARKS.md, "Map file size" (the query paragraph).

A map of the 20 Intel scans the tests ship (0.1 m, hyperparameters given), then
``occupancy`` (interpolated) at ``--points`` uniform points over the scans' extent; the
peak RSS above the RSS before the query (``/proc/self/clear_refs`` resets the kernel's
peak mark). The points' float64 copy and the answer are 24 bytes a point in 2D of it.
Compare two checkouts with ``PYTHONPATH=/path/to/checkout``.

    .venv/bin/python tools/bench_query_rss.py
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans

INTEL20 = Path(__file__).resolve().parents[1] / "tests" / "data" / "intel_first20.log"


def status_mb(field: str) -> float:
    """A ``/proc/self/status`` field (``VmRSS``, ``VmHWM``), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1e3
    return float("nan")


def main() -> None:
    """Print the peak RSS the query adds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=10_000_000)
    args = parser.parse_args()
    scans = list(load_scans(INTEL20))
    hp = Hyperparameters(0.6, 1.0, 0.05, 5.0)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=hp))
    m.insert_scans(scans)
    lo = np.min([s.points.min(axis=0) for s in scans], axis=0)
    hi = np.max([s.points.max(axis=0) for s in scans], axis=0)
    points = np.random.default_rng(0).uniform(lo, hi, (args.points, 2))
    m.occupancy(points[:1000])  # the map settled: the query's own cost only
    Path("/proc/self/clear_refs").write_text("5")
    before = status_mb("VmRSS")
    m.occupancy(points)
    print(
        f"octolgp from {octolgp.__file__}: occupancy at {args.points} points, peak RSS "
        f"{status_mb('VmHWM') - before:.0f} MB above the RSS before the query"
    )


if __name__ == "__main__":
    main()
