"""Whether ``memory_budget_mb`` bounds the process RSS.

Figures: BENCHMARKS.md, "Memory: does the budget bound the process?".

For each budget (and none), in a fresh child process: import octolgp, open the FR079
log (``../shared/data/fr079``; skipped with a note when absent), insert one scan into a
default 2D map at 0.1 m (``MapConfig(dim=2, resolution=0.1, memory_budget_mb=B)``, the
hyperparameters learnt as a user gets them) and read the RSS (the *base*: import plus a
one-scan warm-up), then insert the first ``--scans`` scans and read the peak RSS
(``ru_maxrss``). The target: peak <= base + 1.5 x budget. The *learnt* columns read
the RSS and the peak right after the scan that ends the learning phase (the
hyperparameters learnt on the buffered ``learn_scans`` scans, which are then fitted),
to tell that one-off step from the growth of the map after it.

    .venv/bin/python tools/bench_budget_rss.py --scans 1500 --budgets 64,none
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

FR079 = Path(__file__).resolve().parents[2] / "shared/data/fr079/freiburg-079-corrected.log.gz"


def rss_mb() -> float:
    """Current resident set size, MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1e3
    return float("nan")


def child(scans: int, budget: str) -> None:
    from octolgp import MapConfig, OnlineMap, load_scans

    b = None if budget == "none" else float(budget)
    stream = load_scans(FR079)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, memory_budget_mb=b))
    m.insert_scan(next(stream))
    base = rss_mb()
    learnt: tuple[float, float] | None = None
    t = time.perf_counter()
    for i, s in enumerate(stream, start=2):  # one scan at a time, never a list
        m.insert_scan(s)
        if learnt is None and not m.provisional:
            learnt = (rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3)
        if i >= scans:
            break
    seconds = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    leaves_mb = m.memory_bytes() / 1e6
    m.close()
    learnt_rss, learnt_peak = learnt if learnt is not None else (float("nan"), float("nan"))
    print(
        json.dumps(
            {
                "base": base,
                "peak": peak,
                "learnt_rss": learnt_rss,
                "learnt_peak": learnt_peak,
                "leaves_mb": leaves_mb,
                "seconds": seconds,
            }
        )
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=1500)
    parser.add_argument("--budgets", default="64,none")
    parser.add_argument("--child", nargs=2)
    args = parser.parse_args()
    if args.child:
        child(int(args.child[0]), args.child[1])
        return 0
    if not FR079.exists():
        print(f"skipped: {FR079} is absent (../shared/data is not part of a user's clone)")
        return 0
    print(
        f"`tools/bench_budget_rss.py {' '.join(sys.argv[1:])}`: FR079, first {args.scans} "
        "scans, 0.1 m, default config"
    )
    print()
    print(
        "| budget MB | base RSS MB (import + 1 scan) | peak RSS MB | peak - base | "
        "target (1.5 x budget) | learnt: RSS / peak so far MB | resident leaves MB | s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for budget in args.budgets.split(","):
        out = subprocess.run(
            [sys.executable, __file__, "--child", str(args.scans), budget],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        target = "-" if budget == "none" else f"<= {1.5 * float(budget):.0f}"
        print(
            f"| {budget} | {r['base']:.0f} | {r['peak']:.0f} | {r['peak'] - r['base']:.0f} | "
            f"{target} | {r['learnt_rss']:.0f} / {r['learnt_peak']:.0f} | "
            f"{r['leaves_mb']:.1f} | {r['seconds']:.0f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
