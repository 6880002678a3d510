"""The cost of streaming an online map to Rerun, against no sink and an earlier sink.

Figures: BENCHMARKS.md, "Rerun streaming" and "The tile view".

Maps the first ``--scans`` scans of the bundled Intel log in one process, ``--repeats``
times, into several maps at once, each scan inserted into every map in turn (the order
rotating), so that load from other processes falls on all alike: with logging off (the null
sink), streaming to a recording file with the Rerun sink of git revision ``--before``
(loaded from ``git show``, opened as that revision's CLI opened it), and with the current
sink (opened as ``octolgp run --rerun-save`` opens it:
:func:`octolgp.sinks.rerun.open_recording` with the default blueprint). Prints one table: median seconds, the ratio to the run without logging
(target ≤ 1.1) and the recording size per scan (target ≤ 30 kB over the whole log).

    .venv/bin/python tools/bench_rerun.py --scans 910 --repeats 1
    .venv/bin/python tools/bench_rerun.py --scans 300 --repeats 2 --before none
    .venv/bin/python tools/bench_rerun.py --scans 910 --repeats 1 --before 0563c95 --probability
    .venv/bin/python tools/bench_rerun.py --scans 80 --repeats 2 --learning
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from octolgp import MapConfig, OnlineConfig, OnlineMap, learn_hyperparameters, load_scans
from octolgp.scan import Scan
from octolgp.sinks import rerun as current

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"
BEFORE = "4f61f61"  # a sink with one Rerun entity per leaf, the tile view's comparison

Opener = Callable[[Path, int], tuple[Any, Any]]  # (rrd, dim) -> (recording, sink)


def sink_at(revision: str) -> ModuleType:
    """``octolgp/sinks/rerun.py`` as it was at a git revision, as a module of its own."""
    source = subprocess.run(
        ["git", "show", f"{revision}:octolgp/sinks/rerun.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    spec = importlib.util.spec_from_loader(f"octolgp_rerun_{revision}", loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    exec(compile(source, f"{revision}:octolgp/sinks/rerun.py", "exec"), module.__dict__)
    return module


def opener(module: ModuleType, rays: int, **options: Any) -> Opener:
    """How ``octolgp run --rerun-save`` of that module's revision opens a recording.

    ``options`` go to the sink (``colors="probability"``: ``--rerun-colors probability``).
    """

    def open_(rrd: Path, dim: int) -> tuple[Any, Any]:
        if "blueprint" in module.open_recording.__code__.co_varnames:
            bp = module.default_blueprint(dim)
            rec, _ = module.open_recording("octolgp-bench", save=rrd, blueprint=bp)
            return rec, module.RerunSink(rec, rays=rays, blueprint=False, **options)
        rec, _ = module.open_recording("octolgp-bench", save=rrd)
        return rec, module.RerunSink(rec, rays=rays)

    return open_


def run_once(scans: list[Scan], config: MapConfig, rrd: Path | None, how: Opener | None) -> float:
    """Seconds to insert all scans (and flush the recording when there is one)."""
    return interleaved(scans, config, {"run": (rrd, how)})["run"]


def interleaved(
    scans: list[Scan], config: MapConfig, runs: dict[str, tuple[Path | None, Opener | None]]
) -> dict[str, float]:
    """Seconds per configuration, each scan inserted into every configuration's map in turn.

    The order rotates with the scan, so load from other processes on a shared machine falls
    on every configuration alike. A map's time is the sum of its ``insert_scan`` calls,
    then its close and its recording's flush and disconnect.
    """
    maps: dict[str, tuple[OnlineMap, Any]] = {}
    for name, (rrd, how) in runs.items():  # one iteration per configuration
        rec, sink = how(rrd, config.dim) if how is not None and rrd is not None else (None, None)
        maps[name] = (OnlineMap(config, sink=sink), rec)
    seconds = dict.fromkeys(runs, 0.0)
    names = list(runs)
    for k, scan in enumerate(scans):  # one iteration per scan
        for i in range(len(names)):
            name = names[(i + k) % len(names)]
            t0 = time.perf_counter()
            maps[name][0].insert_scan(scan)
            seconds[name] += time.perf_counter() - t0
    for name, (m, rec) in maps.items():  # one iteration per configuration
        t0 = time.perf_counter()
        m.close()
        if rec is not None:
            rec.flush()
            rec.disconnect()
        seconds[name] += time.perf_counter() - t0
    return seconds


def learning_phase(scans: list[Scan], jobs: int, repeats: int) -> None:
    """Seconds of the learning phase with and without the provisional map; prints a table.

    Maps ``scans`` (hyperparameters learnt on the first ``learn_scans``, 40 in 2D) with the
    current sink, ``provisional`` on and off in turn, each streaming to a recording file;
    times the buffered scans, the learning step and the rest apart.
    """
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(n_jobs=jobs))
    learn = config.learn_scans
    spent: dict[bool, list[tuple[float, float, float]]] = {True: [], False: []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeats):  # one pass per setting per repeat, the order alternating
            for provisional in (r % 2 == 0, r % 2 == 1):
                rec, _ = current.open_recording("octolgp-bench", save=Path(tmp) / f"{r}.rrd")
                sink = current.RerunSink(rec, provisional=provisional)
                times = []
                with OnlineMap(config, sink=sink) as m:
                    for scan in scans:  # one iteration per scan
                        t0 = time.perf_counter()
                        m.insert_scan(scan)
                        times.append(time.perf_counter() - t0)
                rec.flush()
                rec.disconnect()
                phases = (sum(times[: learn - 1]), times[learn - 1], sum(times[learn:]))
                spent[provisional].append(phases)
    print(f"Intel lab, first {len(scans)} scans, learning on {learn}, {jobs} threads")
    print(f"| provisional map | scans 1-{learn - 1} s | scan {learn} (learning) s | the rest s |")
    print("|---|---|---|---|")
    for provisional in (False, True):
        med = np.median(np.array(spent[provisional]), axis=0)
        print(f"| {'on' if provisional else 'off'} | {med[0]:.2f} | {med[1]:.2f} | {med[2]:.2f} |")
    print("runs (s): " + "; ".join(f"{k}: {v}" for k, v in spent.items()))


def main() -> int:
    """Run the rounds and print the table."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--rays", type=int, default=0, help="also log every k-th beam")
    parser.add_argument(
        "--before", default=BEFORE, help=f"git revision to compare with (default {BEFORE}; none)"
    )
    parser.add_argument(
        "--probability",
        action="store_true",
        help="also run the current sink with colors='probability' (--rerun-colors probability)",
    )
    parser.add_argument(
        "--learning",
        action="store_true",
        help="time the learning phase (hyperparameters learnt) with and without the "
        "provisional map instead",
    )
    args = parser.parse_args()
    scans = list(load_scans(INTEL))[: args.scans]
    if args.learning:
        learning_phase(scans, args.jobs, args.repeats)
        return 0
    # fits in insert_scan in every map: a map with a sink never defers them (OnlineConfig.defer_fit)
    online = OnlineConfig(n_jobs=args.jobs, defer_fit=False)
    config = MapConfig(dim=2, resolution=0.1, online=online)
    hp = learn_hyperparameters(scans[:10], config)
    config = dataclasses.replace(config, hyperparameters=hp)
    runs: dict[str, Opener | None] = {"off (null sink)": None}
    if args.before != "none":
        runs[f"Rerun sink at {args.before}"] = opener(sink_at(args.before), args.rays)
    runs["Rerun sink now"] = opener(current, args.rays)
    if args.probability:
        runs["Rerun sink now, probability colours"] = opener(
            current, args.rays, colors="probability"
        )
    seconds: dict[str, list[float]] = {name: [] for name in runs}
    sizes: dict[str, list[int]] = {name: [] for name in runs}
    names = list(runs)
    run_once(scans[:20], config, None, None)  # warm-up: thread pool, BLAS, imports
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):  # one interleaved pass over the scans per repeat
            files = {name: Path(tmp) / f"run{r}_{i}.rrd" for i, name in enumerate(names)}
            spent = interleaved(scans, config, {n: (files[n], runs[n]) for n in names})
            for name in names:  # one iteration per configuration
                seconds[name].append(spent[name])
                rrd = files[name]
                sizes[name].append(rrd.stat().st_size if rrd.exists() else 0)
                rrd.unlink(missing_ok=True)
    n = len(scans)
    t_off = float(np.median(seconds[names[0]]))
    print(f"Intel lab, first {n} scans, 0.1 m, {args.jobs} threads, rays every {args.rays}")
    print("| logging | median s | per scan ms | ratio to off | recording MB | kB per scan |")
    print("|---|---|---|---|---|---|")
    for name in names:
        t = float(np.median(seconds[name]))
        size = float(np.median(sizes[name]))
        rec = "" if runs[name] is None else f"{size / 1e6:.1f}"
        per = "" if runs[name] is None else f"{size / n / 1e3:.1f}"
        print(f"| {name} | {t:.2f} | {1e3 * t / n:.1f} | {t / t_off:.3f} | {rec} | {per} |")
    print("runs (s): " + "; ".join(f"{k}: {[round(v, 2) for v in s]}" for k, s in seconds.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
