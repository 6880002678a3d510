"""Long-mission memory benchmark: peak RSS under a leaf budget vs unbounded.

Figures: BENCHMARKS.md, "Long missions".

Each configuration runs in its own child process (so peak RSS is its own): the
map is written through to a map file, with ``MapConfig(memory_budget_mb=B)`` or
without a budget. The scans are streamed, never held in a list. The parent then
opens the map files and checks that every bounded map equals the unbounded one
at every voxel.

Missions:

``fr079``
    The FR079 CARMEN log (``../shared/data/fr079``, 4,791 scans) replayed twice,
    0.1 m. Skipped with a note when ``../shared/data`` is absent.
``mission3d``
    :func:`octolgp.mission.simulate_mission3d`: a 2 km loop through a street of
    buildings, poles and trees, a 60 × 4-beam lidar every 2 m (1,000 scans), 0.5 m;
    ``OCTOLGP_MISSION_SPACING=8`` drives the same 2 km with a scan every 8 m.

    .venv/bin/python tools/bench_memory.py --missions fr079,mission3d --budgets 64,16
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FR079 = ROOT.parent / "shared" / "data" / "fr079" / "freiburg-079-corrected.log.gz"


def _rss_mb() -> float:
    """Current resident set size, MB."""
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * resource.getpagesize() / 1e6


def _scans(mission: str) -> Iterator[object]:
    from octolgp import load_scans
    from octolgp.sim.mission import simulate_mission3d

    if mission == "fr079":
        for _ in range(2):  # replayed twice, streamed each time
            yield from load_scans(FR079)
    else:
        spacing = float(os.environ.get("OCTOLGP_MISSION_SPACING", "2.0"))
        yield from simulate_mission3d(2000.0, spacing=spacing, n_azimuth=60, n_elevation=4).scans()


def _config(mission: str, hp: dict[str, float], budget: float | None) -> object:
    from octolgp import Hyperparameters, MapConfig

    dim, res = (2, 0.1) if mission == "fr079" else (3, 0.5)
    return MapConfig(
        dim=dim, resolution=res, hyperparameters=Hyperparameters(**hp), memory_budget_mb=budget
    )


def child(mission: str, out: str, budget: float | None, hp: dict[str, float]) -> None:
    """Map the mission into ``out``; print one JSON line with the measurements."""
    import itertools

    from octolgp import OnlineMap

    config = _config(mission, hp, budget)
    it = _scans(mission)
    first = next(it)
    base = _rss_mb()  # interpreter, numpy/scipy, the reader, before any leaf
    t0 = time.perf_counter()
    n, peak_leaf = 0, 0
    with OnlineMap(config, path=out) as m:  # type: ignore[arg-type]
        for scan in itertools.chain([first], it):  # one iteration per scan
            m.insert_scan(scan)  # type: ignore[arg-type]
            n += 1
            peak_leaf = max(peak_leaf, m.memory_bytes())
        leaves, evictions, loads = len(m.store), m.store.evictions, m.store.loads
        resident = m.memory_bytes()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # kB on Linux
    print(
        json.dumps(
            {
                "scans": n,
                "seconds": time.perf_counter() - t0,
                "base_rss_mb": base,
                "peak_rss_mb": peak,
                "peak_leaf_mb": peak_leaf / 1e6,
                "resident_mb": resident / 1e6,
                "leaves": leaves,
                "evictions": evictions,
                "loads": loads,
            }
        )
    )


def _learn(mission: str) -> dict[str, float]:
    import itertools

    from octolgp import Hyperparameters, MapConfig, learn_hyperparameters

    if mission == "mission3d":  # fixed, sane values: this benchmark is about memory
        hp = Hyperparameters(2.0, 1.0, 0.05, 5.0, 0.0)
    else:
        first = list(itertools.islice(_scans(mission), 10))
        hp = learn_hyperparameters(first, MapConfig(dim=2, resolution=0.1))  # type: ignore[arg-type]
    return {f: getattr(hp, f) for f in hp.__dataclass_fields__}


def _probs(path: Path) -> dict[int, np.ndarray]:
    from octolgp.persist.mapfile import decode_leaf

    con = sqlite3.connect(path)
    out = {int(k): decode_leaf(b).prob for k, b in con.execute("SELECT key, data FROM leaves")}
    con.close()
    return out


def main() -> int:
    """Run the children in parallel per mission, print the table, compare the maps."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--missions", default="fr079,mission3d")
    parser.add_argument("--budgets", default="64,16", help="MB, comma-separated")
    parser.add_argument("--child", nargs=3, metavar=("MISSION", "OUT", "BUDGET"))
    parser.add_argument("--hp", default=None)
    args = parser.parse_args()
    if args.child:
        mission, out, budget = args.child
        child(mission, out, None if budget == "none" else float(budget), json.loads(args.hp))
        return 0
    budgets = ["none", *args.budgets.split(",")]
    for mission in args.missions.split(","):
        if mission == "fr079" and not FR079.is_file():
            print(f"\n## {mission}: skipped, {FR079} is absent (it lives in ../shared/data)")
            continue
        hp = _learn(mission)
        with tempfile.TemporaryDirectory() as tmp:
            procs = {}
            for b in budgets:  # all budgets at once, one process each
                out = Path(tmp) / f"{mission}-{b}.octolgp"
                cmd = [sys.executable, __file__, "--child", mission, str(out), b]
                procs[b] = (
                    out,
                    subprocess.Popen(
                        [*cmd, "--hp", json.dumps(hp)], stdout=subprocess.PIPE, text=True
                    ),
                )
            rows = {}
            for b, (_out, p) in procs.items():
                stdout, _ = p.communicate()
                if p.returncode != 0:
                    raise SystemExit(f"child {mission} budget {b} failed")
                rows[b] = json.loads(stdout.strip().splitlines()[-1])
            ref = _probs(procs["none"][0])
            print(f"\n## {mission}: {rows['none']['scans']} scans, hyperparameters {hp}")
            print(
                "| budget MB | peak RSS MB | RSS before mapping MB | peak leaf RAM MB | "
                "leaves | evictions | loads | s | equal to unbounded |"
            )
            print("|---|---|---|---|---|---|---|---|---|")
            for b, r in rows.items():
                probs = _probs(procs[b][0])
                same = probs.keys() == ref.keys() and all(
                    np.array_equal(probs[k], ref[k]) for k in ref
                )
                print(
                    f"| {b} | {r['peak_rss_mb']:.0f} | {r['base_rss_mb']:.0f} | "
                    f"{r['peak_leaf_mb']:.1f} | {r['leaves']} | {r['evictions']} | "
                    f"{r['loads']} | {r['seconds']:.0f} | {'yes' if same else 'NO'} |"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
