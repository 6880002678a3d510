"""The KITTI fixture's insert against OctoMap's, with and without a heap trim before each map.

``tools/bench_3d.py`` hands the heap back to the system (glibc ``malloc_trim``) before each
leave-one-out split so that each run's peak RSS is its own; a map's first inserts after that
pay page faults for their working arrays. This bench maps the fixture's first four scans into
a fresh ``OnlineMap`` (the default config, hyperparameters given) and a fresh OctoMap
(``pyoctomap``), alternately, many times, with the trim before each pair of maps (as
``bench_3d``) and without it (a process mapping on), and prints the median insert per scan
index and overall, and the ratio in the same run.

Run from the repository root::

    .venv/bin/python tools/bench_kitti_heap.py [--rounds 60]
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
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


def trim_heap() -> None:
    """Collect garbage and return the heap's free pages to the system (as ``bench_3d``)."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def rounds(n: int, trim: bool) -> tuple[np.ndarray, np.ndarray]:
    """Insert seconds, shape (n, 4), of octolgp and of OctoMap: ``n`` fresh pairs of maps."""
    scans = scene_scans("kitti")[:4]
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP)
    ours, theirs = np.zeros((n, len(scans))), np.zeros((n, len(scans)))
    for r in range(n):  # one fresh pair of maps per round
        if trim:
            trim_heap()
        m, ref = OnlineMap(config), OctomapReference(0.2, 3)
        for i, scan in enumerate(scans):  # the two maps take turns, the order swapping
            for who in ("octolgp", "octomap") if (r + i) % 2 == 0 else ("octomap", "octolgp"):
                t0 = time.perf_counter()
                if who == "octolgp":
                    m.insert_scan(scan)
                    ours[r, i] = time.perf_counter() - t0
                else:
                    ref.insert_scan(scan)
                    theirs[r, i] = time.perf_counter() - t0
        m.close()
    return ours, theirs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=60, help="fresh pairs of maps (60)")
    args = parser.parse_args()
    if not octomap_available():
        sys.exit("pyoctomap is not installed: `pip install pyoctomap`")
    print("# The KITTI fixture: octolgp against OctoMap, with and without a heap trim per map")
    print(f"Command: `.venv/bin/python tools/bench_kitti_heap.py --rounds {args.rounds}`")
    print(f"Machine: {platform.machine()}, Python {platform.python_version()}")
    print("octolgp: `MapConfig(dim=3, resolution=0.2)` with hyperparameters given; the first")
    print("round of each kind is left out (numba's kernels load).\n")
    print(
        "| heap | octolgp ms, inserts 1 / 2 / 3 / 4 | OctoMap ms, inserts 1 / 2 / 3 / 4 "
        "| octolgp median ms | OctoMap median ms | octolgp / OctoMap |"
    )
    print("|---|---|---|---|---|---|")
    for trim in (True, False):
        ours, theirs = rounds(args.rounds + 1, trim)
        ours, theirs = ours[1:] * 1e3, theirs[1:] * 1e3
        a, b = np.median(ours, axis=0), np.median(theirs, axis=0)
        mo, mt = float(np.median(ours)), float(np.median(theirs))
        name = "trimmed before each map (as bench_3d)" if trim else "not trimmed"
        print(
            f"| {name} | {' / '.join(f'{x:.2f}' for x in a)} | {' / '.join(f'{x:.2f}' for x in b)} "
            f"| {mo:.2f} | {mt:.2f} | {mo / mt:.2f}x |"
        )


if __name__ == "__main__":
    main()
