"""Whether ``memory_budget_mb`` bounds the process RSS over a long mission, 2D and 3D.

Figures: BENCHMARKS.md, "Memory: does the budget bound the process?".

Missions (default config, each in a fresh child process per budget):

- ``2d``: the first ``--scans`` scans of FR079 (``../shared/data/fr079``; skipped with
  a note when absent), ``MapConfig(dim=2, resolution=0.1, memory_budget_mb=B)``, the
  hyperparameters learnt as a user gets them;
- ``3d``: ``--scans3d`` scans of :func:`octolgp.sim.mission.simulate_mission3d` (a
  street loop, a 90 x 8 lidar to 20 m, a scan every metre, so the map grows all mission
  long), each through ``Scan.downsample(0.2)``, ``MapConfig(dim=3, resolution=0.2,
  memory_budget_mb=B)``.

The *base* is the RSS after importing octolgp and a one-scan warm-up: one scan inserted
into a throwaway map with hyperparameters given, and read, so that the code's one-off
costs (numba's compiler and compiled kernels, about 100 MB; the lattice tables) are in
it. Then the mission's map is built scan by scan and the peak RSS since the base read
(``VmHWM``, reset at the base: :mod:`octolgp.memory`).
The target: peak <= base + 1.5 x budget. The table gives the RSS right after the
learning step, at the end, and whether it is flat over the second half (the largest
rise of the RSS read every 50 scans over the second half), the leaves resident in RAM,
the map file's (or spill file's) bytes per scan and per observed voxel (a voxel some
scan saw, counted once in its own leaf), and the seconds; ``--plot PNG`` draws
the per-scan insert time over the mission.

    .venv/bin/python tools/bench_budget_rss.py --scans 1500 --scans3d 2000 --budgets 64,none
"""

from __future__ import annotations

import argparse
import gc
import itertools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

FR079 = Path(__file__).resolve().parents[2] / "shared/data/fr079/freiburg-079-corrected.log.gz"


def mission(kind: str, scans: int):  # type: ignore[no-untyped-def]
    """The mission's config (without a budget) and its scans, streamed."""
    from octolgp import MapConfig, load_scans
    from octolgp.sim.mission import simulate_mission3d

    if kind == "2d":
        stream = load_scans(FR079)
        return MapConfig(dim=2, resolution=0.1), itertools.islice(stream, scans)
    m3 = simulate_mission3d(float(scans) + 5.0, seed=0, spacing=1.0)
    return MapConfig(dim=3, resolution=0.2), (m3.scan(k).downsample(0.2) for k in range(scans))


def child(kind: str, scans: int, budget: str) -> None:
    """One mission in this process; prints a JSON line of its figures."""
    import dataclasses

    from octolgp import Hyperparameters, OnlineMap
    from octolgp.memory import peak_rss_mb, reset_peak_rss, rss_mb

    b = None if budget == "none" else float(budget)
    config, stream = mission(kind, scans)
    first = next(stream)
    warm = OnlineMap(dataclasses.replace(config, hyperparameters=Hyperparameters()))
    warm.insert_scan(first)
    warm.occupancy(first.points[:10])
    warm.close()
    del warm
    gc.collect()
    base = rss_mb()
    reset_peak_rss()
    m = OnlineMap(dataclasses.replace(config, memory_budget_mb=b))
    learnt, samples, times = float("nan"), [], []
    t0 = time.perf_counter()
    for i, s in enumerate(_chain(first, stream), start=1):  # one scan at a time
        t = time.perf_counter()
        update = m.insert_scan(s)
        times.append(time.perf_counter() - t)
        if "learning" in update.stages:
            learnt = rss_mb()
        if i % 50 == 0:
            samples.append((i, rss_mb()))
    m.occupancy(first.points)  # a read: the deferred fits are paid
    seconds = time.perf_counter() - t0
    end, peak = rss_mb(), peak_rss_mb()
    half = [r for i, r in samples if i >= scans // 2]
    rise = max(half) - half[0] if half else float("nan")
    path = m.path  # the spill file of a budget
    file_bytes, observed = 0, 0
    if path is not None:
        file_bytes = sum(os.path.getsize(p) for p in (path, f"{path}-wal") if os.path.exists(p))
        from bench_file_size import observed_voxels  # this folder: a tool beside it

        observed = observed_voxels(Path(path))
    leaves_mb = m.memory_bytes() / 1e6
    m.close()
    print(
        json.dumps(
            {
                "base": base,
                "peak": peak,
                "learnt": learnt,
                "end": end,
                "rise": rise,
                "leaves_mb": leaves_mb,
                "file_per_scan_kb": file_bytes / scans / 1e3,
                "file_per_voxel": file_bytes / observed if observed else float("nan"),
                "seconds": seconds,
                "times": times,
            }
        )
    )


def _chain(first, stream):  # type: ignore[no-untyped-def]
    yield first
    yield from stream


def main() -> int:
    """Print the table (and draw the plot)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=1500, help="2D scans (FR079; 0: none)")
    parser.add_argument("--scans3d", type=int, default=2000, help="3D scans (0: none)")
    parser.add_argument("--budgets", default="64,none")
    parser.add_argument("--plot", type=Path, default=None, help="per-scan time over the mission")
    parser.add_argument("--child", nargs=3)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]), args.child[2])
        return 0
    runs = []
    if not args.scans:
        pass
    elif FR079.exists():
        runs.append(("2d", args.scans))
    else:
        print(f"2d skipped: {FR079} is absent (../shared/data is not part of a user's clone)")
    if args.scans3d:
        runs.append(("3d", args.scans3d))
    print(f"`tools/bench_budget_rss.py {' '.join(sys.argv[1:])}`, default config")
    print()
    print(
        "| mission | scans | budget MB | base RSS MB (import + warm-up) | peak RSS MB | "
        "peak - base | target (1.5 x budget) | RSS after learning MB | end RSS MB | rise over "
        "the second half MB | resident leaves MB | file kB / scan | file B / observed voxel | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    series = {}
    for kind, n in runs:
        for budget in args.budgets.split(","):
            out = subprocess.run(
                [sys.executable, __file__, "--child", kind, str(n), budget],
                capture_output=True,
                text=True,
                check=True,
            )
            r = json.loads(out.stdout.strip().splitlines()[-1])
            series[(kind, budget)] = r["times"]
            target = "-" if budget == "none" else f"<= {1.5 * float(budget):.0f}"
            print(
                f"| {kind} | {n} | {budget} | {r['base']:.0f} | {r['peak']:.0f} | "
                f"{r['peak'] - r['base']:.0f} | {target} | {r['learnt']:.0f} | {r['end']:.0f} | "
                f"{r['rise']:.0f} | {r['leaves_mb']:.1f} | {r['file_per_scan_kb']:.1f} | "
                f"{r['file_per_voxel']:.1f} | {r['seconds']:.0f} |",
                flush=True,
            )
    if args.plot is not None and series:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(len(runs), 1, figsize=(8, 3 * len(runs)), squeeze=False)
        for ax, (kind, _) in zip(axes[:, 0], runs, strict=True):
            for (k, budget), times in series.items():
                if k == kind:
                    ax.plot([1e3 * t for t in times], lw=0.6, label=f"budget {budget}")
            ax.set_yscale("log")
            ax.set_xlabel("scan")
            ax.set_ylabel("insert ms")
            ax.set_title(f"{kind} mission: insert time per scan")
            ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"\nplot: {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
