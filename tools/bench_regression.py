"""Speed of the online map against an earlier commit, in one run.

Figures: BENCHMARKS.md, "Core rebuild".

The same measurement as ``tools/bench_online.py --parts replay`` (Intel lab, 0.1 m,
hyperparameters learnt on the first 10 scans, ``n_jobs`` threads), on the first
``--scans`` scans, for the octolgp of ``--baseline`` (exported with ``git archive``)
and of the working tree, alternating ``--repeats`` times so that machine noise hits
both alike. Prints the median ``insert_scan`` time of each run and the ratio of the
medians (working tree / baseline). Only the public API is used, so both trees run
the same code here.

``--scene 3dtk``: the 3DTK fixture ``tests/data/3dtk`` instead (3 scans at 0.2 m,
downsampled to 0.2 m, given hyperparameters, each scan inserted into a fresh map per
repeat of ``--scans`` passes), the 3D path's per-leaf bookkeeping.

Run from the repository root::

    .venv/bin/python tools/bench_regression.py --baseline 89ae9f4
    .venv/bin/python tools/bench_regression.py --baseline 89ae9f4 --scene 3dtk
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

DRIVER = """
import dataclasses, json, sys
import numpy as np
import octolgp
from octolgp import MapConfig, OnlineConfig, OnlineMap, learn_hyperparameters, load_scans
scans = list(load_scans(sys.argv[1]))[: int(sys.argv[2])]
config = MapConfig(dim=2, resolution=0.1)
hp = learn_hyperparameters(scans[:10], config)
online = dataclasses.replace(config.online, n_jobs=int(sys.argv[3]))
m = OnlineMap(dataclasses.replace(config, hyperparameters=hp, online=online))
sec = [m.insert_scan(s).seconds for s in scans]
print(json.dumps({"file": octolgp.__file__, "seconds": sec}))
"""

DRIVER_3D = """
import json, sys
import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, load_scans
scans = [s.downsample(0.2) for s in load_scans(sys.argv[1])]
hp = Hyperparameters(length_scale=1.0, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp,
                   online=OnlineConfig(n_jobs=int(sys.argv[3])))
sec = []
for _ in range(int(sys.argv[2])):
    m = OnlineMap(config)
    sec += [m.insert_scan(s).seconds for s in scans]
    m.close()
print(json.dumps({"file": octolgp.__file__, "seconds": sec}))
"""


def run(tree: Path, log: Path, scans: int, jobs: int, driver: str = DRIVER) -> list[float]:
    """Per-scan insert seconds of the octolgp under ``tree``."""
    out = subprocess.run(
        [sys.executable, "-P", "-c", driver, str(log), str(scans), str(jobs)],
        env={**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"},
        cwd=tree,
        check=True,
        capture_output=True,
        text=True,
    )
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if not result["file"].startswith(str(tree)):
        raise SystemExit(f"imported {result['file']}, not the octolgp under {tree}")
    return list(result["seconds"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="89ae9f4", help="commit to compare against")
    parser.add_argument("--scans", type=int, default=300, help="first N Intel scans")
    parser.add_argument("--jobs", type=int, default=2, help="threads refitting leaves")
    parser.add_argument("--repeats", type=int, default=2, help="alternating runs per side")
    parser.add_argument("--scene", choices=["intel", "3dtk"], default="intel")
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
        print(f"{title}, n_jobs={args.jobs}")
        print("| run | side | median ms | mean ms | p90 ms |")
        print("|---|---|---|---|---|")
        for r in range(args.repeats):  # alternate the sides
            for name, tree in sides.items():
                sec = 1e3 * np.array(run(tree, log, args.scans, args.jobs, driver))
                medians[name].append(float(np.median(sec)))
                print(
                    f"| {r + 1} | {name} | {np.median(sec):.1f} | {sec.mean():.1f} | "
                    f"{np.percentile(sec, 90):.1f} |",
                    flush=True,
                )
    b, w = (float(np.median(v)) for v in medians.values())
    print(f"median of run medians: baseline {b:.1f} ms, working tree {w:.1f} ms, ratio {w / b:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
