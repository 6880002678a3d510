"""Speed of the online map against an earlier commit, in one run.

Figures: BENCHMARKS.md, "Core rebuild".

The same measurement as ``tools/bench_online.py --parts replay`` (Intel lab, 0.1 m,
hyperparameters learnt on the first 10 scans, ``n_jobs`` threads), on the first
``--scans`` scans, for the octolgp of ``--baseline`` (exported with ``git archive``)
and of the working tree, alternating ``--repeats`` times so that machine noise hits
both alike. Prints the median ``insert_scan`` time of each run and the ratio of the
medians (working tree / baseline). Only the public API is used, so both trees run
the same code here.

``--file``: every map has a file, so each insert is committed (WAL, ``synchronous=FULL``):
the cost of the file's guarantees (the checksums' share of the insert time is timed
in the same run).

``--scene 3dtk``: the 3DTK fixture ``tests/data/3dtk`` instead (3 scans at 0.2 m,
downsampled to 0.2 m, given hyperparameters, each scan inserted into a fresh map per
repeat of ``--scans`` passes), the 3D path's per-leaf bookkeeping.

Run from the repository root::

    .venv/bin/python tools/bench_regression.py --baseline 89ae9f4
    .venv/bin/python tools/bench_regression.py --baseline 89ae9f4 --scene 3dtk
    .venv/bin/python tools/bench_regression.py --baseline 42762a2 --file
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from compare_maps import REPO, export_tree

TIMED_CRC = """
import time, zlib
import octolgp.persist.mapfile as mapfile
crc_seconds = [0.0]
class _TimedZlib:
    @staticmethod
    def crc32(data, value=0):
        t = time.perf_counter()
        out = zlib.crc32(data, value)
        crc_seconds[0] += time.perf_counter() - t
        return out
if hasattr(mapfile, "zlib"):  # checksums exist in this tree: time them
    mapfile.zlib = _TimedZlib
def where(n):
    return None if sys.argv[4] == "-" else f"{sys.argv[4]}/map-{n}.octolgp"
"""

DRIVER = (
    """
import dataclasses, json, sys
import numpy as np
import octolgp
from octolgp import MapConfig, OnlineConfig, OnlineMap, learn_hyperparameters, load_scans
"""
    + TIMED_CRC
    + """
scans = list(load_scans(sys.argv[1]))[: int(sys.argv[2])]
config = MapConfig(dim=2, resolution=0.1)
hp = learn_hyperparameters(scans[:10], config)
online = dataclasses.replace(config.online, n_jobs=int(sys.argv[3]))
m = OnlineMap(dataclasses.replace(config, hyperparameters=hp, online=online), where(0))
sec = [m.insert_scan(s).seconds for s in scans]
m.close()
print(json.dumps({"file": octolgp.__file__, "seconds": sec, "crc": crc_seconds[0]}))
"""
)

DRIVER_3D = (
    """
import json, sys
import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, load_scans
"""
    + TIMED_CRC
    + """
scans = [s.downsample(0.2) for s in load_scans(sys.argv[1])]
hp = Hyperparameters(length_scale=1.0, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp,
                   online=OnlineConfig(n_jobs=int(sys.argv[3])))
sec = []
for n in range(int(sys.argv[2])):
    m = OnlineMap(config, where(n))
    sec += [m.insert_scan(s).seconds for s in scans]
    m.close()
print(json.dumps({"file": octolgp.__file__, "seconds": sec, "crc": crc_seconds[0]}))
"""
)


def run(
    tree: Path, log: Path, scans: int, jobs: int, driver: str = DRIVER, folder: str = "-"
) -> tuple[list[float], float]:
    """Per-scan insert seconds of the octolgp under ``tree``, and the seconds in CRC-32.

    ``folder``: where the maps' files go (``"-"``: maps in memory).
    """
    out = subprocess.run(
        [sys.executable, "-P", "-c", driver, str(log), str(scans), str(jobs), folder],
        env={**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"},
        cwd=tree,
        check=True,
        capture_output=True,
        text=True,
    )
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if not result["file"].startswith(str(tree)):
        raise SystemExit(f"imported {result['file']}, not the octolgp under {tree}")
    return list(result["seconds"]), float(result["crc"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="89ae9f4", help="commit to compare against")
    parser.add_argument("--scans", type=int, default=300, help="first N Intel scans")
    parser.add_argument("--jobs", type=int, default=2, help="threads refitting leaves")
    parser.add_argument("--repeats", type=int, default=2, help="alternating runs per side")
    parser.add_argument("--scene", choices=["intel", "3dtk"], default="intel")
    parser.add_argument(
        "--file", action="store_true", help="maps with a file (every insert committed)"
    )
    args = parser.parse_args()
    log = REPO / "data" / "intel_lab" / "intel-corrected.log.gz"
    driver, title = DRIVER, f"Intel, first {args.scans} scans, 0.1 m, hp on 10 scans"
    if args.scene == "3dtk":
        log = REPO / "tests" / "data" / "3dtk"
        driver = DRIVER_3D
        title = f"3DTK fixture, 3 scans x {args.scans} passes, 0.2 m, hp given"
    with tempfile.TemporaryDirectory(prefix="bench_regression_") as tmp:
        base = Path(tmp) / "baseline"
        full = export_tree(args.baseline, base)
        sides = {f"baseline {full[:7]}": base, "working tree": REPO}
        medians: dict[str, list[float]] = {name: [] for name in sides}
        where = "with a map file" if args.file else "in memory"
        print(f"{title}, n_jobs={args.jobs}, {where}")
        print("| run | side | median ms | mean ms | p90 ms | CRC-32 share |")
        print("|---|---|---|---|---|---|")
        for r in range(args.repeats):  # alternate the sides
            for name, tree in sides.items():
                with tempfile.TemporaryDirectory(dir=tmp) as maps:
                    folder = maps if args.file else "-"
                    seconds, crc = run(tree, log, args.scans, args.jobs, driver, folder)
                sec = 1e3 * np.array(seconds)
                medians[name].append(float(np.median(sec)))
                print(
                    f"| {r + 1} | {name} | {np.median(sec):.1f} | {sec.mean():.1f} | "
                    f"{np.percentile(sec, 90):.1f} | {1e3 * crc / sec.sum():.2%} |",
                    flush=True,
                )
    b, w = (float(np.median(v)) for v in medians.values())
    print(f"median of run medians: baseline {b:.1f} ms, working tree {w:.1f} ms, ratio {w / b:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
