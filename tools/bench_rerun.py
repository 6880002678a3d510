"""Benchmark: the cost of streaming an online map to Rerun (issue #4).

Maps the first ``--scans`` scans of the bundled Intel log twice in one process,
alternating the order over ``--repeats`` rounds: once with logging off (the null
sink) and once streaming to a recording file (``RerunSink``: every scan's pose and
points, every refitted leaf, the per-scan metrics). Prints the ratio of the wall
times (target ≤ 1.25) and the recording size per scan.

    .venv/bin/python tools/bench_rerun.py --scans 300 --repeats 2
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rerun as rr

from octolgp import MapConfig, OnlineConfig, OnlineMap, learn_hyperparameters, load_scans
from octolgp.scan import Scan
from octolgp.sinks.rerun import RerunSink

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"


def run_once(scans: list[Scan], config: MapConfig, rrd: Path | None, rays: int) -> float:
    """Seconds to insert all scans (and flush the recording when there is one)."""
    rec = None
    sink = None
    if rrd is not None:
        rec = rr.RecordingStream("octolgp-bench")
        rec.save(rrd)
        sink = RerunSink(rec, rays=rays)
    t0 = time.perf_counter()
    with OnlineMap(config, sink=sink) as m:
        for s in scans:  # one iteration per scan
            m.insert_scan(s)
    if rec is not None:
        rec.flush()
        rec.disconnect()
    return time.perf_counter() - t0


def main() -> int:
    """Run the off/on rounds and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--rays", type=int, default=0, help="also log every k-th beam")
    args = parser.parse_args()
    scans = list(load_scans(INTEL))[: args.scans]
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(n_jobs=args.jobs))
    hp = learn_hyperparameters(scans[:10], config)
    config = dataclasses.replace(config, hyperparameters=hp)
    off, on, sizes = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):  # alternate the order against drift
            rrd = Path(tmp) / f"run{r}.rrd"
            if r % 2 == 0:
                off.append(run_once(scans, config, None, args.rays))
                on.append(run_once(scans, config, rrd, args.rays))
            else:
                on.append(run_once(scans, config, rrd, args.rays))
                off.append(run_once(scans, config, None, args.rays))
            sizes.append(rrd.stat().st_size)
    t_off, t_on = float(np.median(off)), float(np.median(on))
    size = float(np.median(sizes))
    print(
        f"Intel lab, first {len(scans)} scans, 0.1 m, {args.jobs} threads, rays every {args.rays}"
    )
    print("| logging | median s | per scan ms |")
    print("|---|---|---|")
    print(f"| off (null sink) | {t_off:.2f} | {1e3 * t_off / len(scans):.1f} |")
    print(f"| Rerun file sink | {t_on:.2f} | {1e3 * t_on / len(scans):.1f} |")
    print(f"ratio on/off: {t_on / t_off:.3f} (target ≤ 1.25); runs off {off}, on {on}")
    print(f"recording: {size / 1e6:.1f} MB, {size / len(scans) / 1e3:.1f} kB per scan")
    return 0


if __name__ == "__main__":
    sys.exit(main())
