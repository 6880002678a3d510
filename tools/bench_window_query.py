"""A planner's loop: insert a 3D scan, then query a window around the sensor, scan after scan.

Figures: BENCHMARKS.md, "Live 3D, third part". With fits deferred (the default) a query
of up to ``LOCAL_QUERY_POINTS`` points fits only the pending leaves it reads, so a
local window pays for the leaves near the sensor and the far ones wait; fitted at every
insert (``online.defer_fit=False``) every changed leaf is fitted in the insert. Both
maps and OctoMap (``pyoctomap``, insert only) take the same scans in one process, in
turns (the order swaps every scan); the window holds ``--points`` points uniform in a
box of ``--half`` metres around the sensor (a tenth of that vertically). The two maps'
answers are checked equal at the end.

Scenes (``tools/bench_insert_cpu.py``'s, hyperparameters given, length scale 0.8 m):
``room`` and ``street64``.

Run from the repository root::

    .venv/bin/python tools/bench_window_query.py
    .venv/bin/python tools/bench_window_query.py --scenes street64 --points 5000
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_insert_cpu import scene_scans

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.bench.octomap_ref import OctomapReference, octomap_available

HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def run(scene: str, n_points: int, half: float) -> str:
    """One scene: the Markdown row of median seconds per scan (after the first)."""
    scans = scene_scans(scene)
    rng = np.random.default_rng(0)
    base = MapConfig(dim=3, resolution=0.2, hyperparameters=HP)
    maps = {
        defer: OnlineMap(
            dataclasses.replace(base, online=dataclasses.replace(base.online, defer_fit=defer))
        )
        for defer in (True, False)
    }
    ref = OctomapReference(0.2, 3) if octomap_available() else None
    times: dict[object, list[float]] = {True: [], False: [], "octomap": []}
    for i, scan in enumerate(scans):
        box = rng.uniform(-half, half, (n_points, 3)) * np.array([1.0, 1.0, 0.1])
        window = scan.origin + box
        order: tuple[object, ...] = (
            (True, False, "octomap") if i % 2 == 0 else ("octomap", False, True)
        )
        for who in order:
            t = time.perf_counter()
            if who == "octomap":
                if ref is None:
                    continue
                ref.insert_scan(scan)
            else:
                maps[bool(who)].insert_scan(scan)
                maps[bool(who)].occupancy(window)
            times[who].append(time.perf_counter() - t)
    same = np.array_equal(
        maps[True].occupancy(scans[-1].points), maps[False].occupancy(scans[-1].points)
    )
    med = {k: float(np.median(v[1:])) if len(v) > 1 else float("nan") for k, v in times.items()}
    om = med["octomap"]

    def ratio(a: float) -> str:
        return "–" if om != om else f"{a / om:.2f}x"

    return (
        f"| {scene} | {len(scans) - 1} | {med[True]:.3f} | {med[False]:.3f} | {om:.3f} | "
        f"{ratio(med[True])} | {ratio(med[False])} | {'yes' if same else 'NO'} |"
    )


def main(argv: list[str] | None = None) -> int:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="room,street64")
    parser.add_argument("--points", type=int, default=2000, help="query points per scan")
    parser.add_argument("--half", type=float, default=10.0, help="window half-width, metres")
    args = parser.parse_args(argv)
    print("# Insert, then a window query around the sensor, scan after scan (3D, 0.2 m)")
    print(
        f"Command: `.venv/bin/python tools/bench_window_query.py {' '.join(argv or sys.argv[1:])}`"
    )
    print(
        f"Machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}"
    )
    print()
    print(
        "| scene | scans timed | deferred: insert + query s | fitted at every insert: insert + "
        "query s | OctoMap insert s | deferred / OctoMap | at every insert / OctoMap | same answers |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for scene in args.scenes.split(","):
        print(run(scene, args.points, args.half), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
