"""Speed-ups of issue #7 as ratios against the code before it, measured in one run.

The old code is a git revision (default ``591db9f``, the last commit before issue #7)
checked out into a temporary worktree; each workload runs in a fresh child process
importing either that tree or this one, alternating old/new ``--repeats`` times so
that machine noise hits both alike. The same hyperparameters (learnt once, by the
current code) are handed to both, so only speed differs.

Workloads:

``intel``
    Online mapping: the first ``--scans`` scans of the bundled Intel log inserted one
    by one into an ``OnlineMap`` at 0.1 m (``n_jobs=1``): total insert seconds.
``paper2d``
    The paper's 2D benchmark: the simulated data set of ``octolgp simulate paper2d``
    built offline with ``build_map(method="lgp")`` (``n_jobs=1``): build seconds.
``3dtk``
    Online mapping of the three 3DTK scans at 0.2 m (voxel-filtered to 0.2 m), from
    ``tests/data/3dtk`` (a cut of the real scans): total insert seconds.

    .venv/bin/python tools/bench_speedup.py --repeats 3
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
from threadpoolctl import threadpool_limits
import numpy as np
import octolgp
from octolgp import MapConfig, OnlineMap, Hyperparameters, build_map, load_scans
workload, hp = sys.argv[2], Hyperparameters(**json.loads(sys.argv[3]))
n_scans = int(sys.argv[4])
assert octolgp.__file__.startswith(sys.argv[1]), octolgp.__file__
if workload == "intel":
    import itertools
    scans = list(itertools.islice(load_scans(sys.argv[5]), n_scans))
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=hp))
    t = time.perf_counter()
    for s in scans:
        m.insert_scan(s)
    seconds = time.perf_counter() - t
elif workload == "3dtk":
    scans = [s.downsample(0.2) for s in load_scans(sys.argv[5])]
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp))
    t = time.perf_counter()
    for s in scans:
        m.insert_scan(s)
    seconds = time.perf_counter() - t
else:
    from octolgp.sim.scenes import simulate_paper2d
    data = simulate_paper2d(seed=0)
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=hp)
    t = time.perf_counter()
    build_map(data.scans, config, method="lgp", n_jobs=1)
    seconds = time.perf_counter() - t
print(json.dumps({"seconds": seconds}))
"""


def _hp(workload: str, scans: int) -> str:
    """Hyperparameters learnt once by the current code for a workload."""
    import dataclasses
    import itertools

    from octolgp import MapConfig, learn_hyperparameters, load_scans
    from octolgp.sim.scenes import simulate_paper2d

    if workload == "intel":
        data = list(itertools.islice(load_scans(_source("intel")), 40))
        hp = learn_hyperparameters(data, MapConfig(dim=2, resolution=0.1))
    elif workload == "3dtk":
        data = [s.downsample(0.2) for s in load_scans(_source("3dtk"))]
        hp = learn_hyperparameters(data, MapConfig(dim=3, resolution=0.2))
    else:
        hp = learn_hyperparameters(simulate_paper2d(seed=0).scans, MapConfig(dim=2))
    return json.dumps(dataclasses.asdict(hp))


def _source(workload: str) -> str:
    return {
        "intel": str(ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"),
        "3dtk": str(ROOT / "tests" / "data" / "3dtk"),
        "paper2d": "-",
    }[workload]


def _run(tree: Path, workload: str, hp: str, scans: int) -> float:
    cmd = [sys.executable, "-c", CHILD, str(tree), workload, hp, str(scans), _source(workload)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=tree)
    if res.returncode != 0:
        raise SystemExit(f"{tree} {workload} failed:\n{res.stderr[-2000:]}")
    return float(json.loads(res.stdout.strip().splitlines()[-1])["seconds"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", default="591db9f", help="git revision of the old code")
    parser.add_argument("--workloads", default="intel,paper2d,3dtk")
    parser.add_argument("--scans", type=int, default=300, help="Intel scans to insert")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="octolgp-old-") as tmp:
        old = Path(tmp) / "old"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.old],
            check=True,
            capture_output=True,
        )
        try:
            for workload in args.workloads.split(","):
                hp = _hp(workload, args.scans)
                times: dict[str, list[float]] = {"old": [], "new": []}
                for _ in range(args.repeats):  # alternate so noise hits both alike
                    times["old"].append(_run(old, workload, hp, args.scans))
                    times["new"].append(_run(ROOT, workload, hp, args.scans))
                o, n = float(np.median(times["old"])), float(np.median(times["new"]))
                rows.append((workload, o, n, times))
                print(f"{workload}: old {o:.2f} s, new {n:.2f} s, x{o / n:.2f}", file=sys.stderr)
        finally:
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                check=False,
                capture_output=True,
            )
    print(f"\nold = git revision {args.old}; median of {args.repeats} alternating runs each")
    print("| workload | old s | new s | speed-up (old / new) | all old | all new |")
    print("|---|---|---|---|---|---|")
    for workload, o, n, times in rows:
        print(
            f"| {workload} | {o:.2f} | {n:.2f} | {o / n:.2f}x | "
            f"{', '.join(f'{t:.2f}' for t in times['old'])} | "
            f"{', '.join(f'{t:.2f}' for t in times['new'])} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
