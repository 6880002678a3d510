"""Held-out AUC of the online map's leaf engines on a log, in one run.

Figures: BENCHMARKS.md, "Held-out AUC: lattice against exact, same splits, same
hyperparameters" and "Held-out AUC with forgetting on the real logs".

For each engine (``lattice``, the default, and ``exact``, the paper's local GP with
integral kernels) and each seed, ``octolgp eval``'s protocol (10 % of the scans held
out in runs of 40, endpoints occupied, points along the beams free), the online map
built in one step (the same map as inserting the scans one by one). Hyperparameters
are learnt once per split on the first ``learn_scans`` training scans and shared by
both engines. Extra variants: ``--variant "lattice.free_weight=0.5"`` (settings
``SECTION.FIELD=VALUE`` separated by ``;``).

    .venv/bin/python tools/bench_engines.py data/intel_lab/intel-corrected.log.gz --seeds 3
    .venv/bin/python tools/bench_engines.py --paper --seeds 5

``--paper``: the paper's 2D simulation instead of a log (``simulate_paper2d(seed)``, 0.2 m,
its exact cell labels as test points, hyperparameters learnt on all its scans as the
paper's Table II does), one simulated data set per seed.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from bench_2d_online import config_of

from octolgp import load_scans
from octolgp.bench.evaluation import evaluate_log


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path, nargs="?")
    parser.add_argument("--paper", action="store_true", help="the paper's 2D simulation")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--variant", action="append", default=[])
    parser.add_argument("--no-exact", action="store_true", help="skip the exact engine's row")
    args = parser.parse_args()
    if args.paper:
        return paper(args.seeds, args.variant, not args.no_exact)
    scans = list(load_scans(args.log))
    variants = ["", *([] if args.no_exact else ["online.engine=exact"]), *args.variant]
    print(f"`{' '.join(['tools/bench_engines.py', *sys.argv[1:]])}`")
    cpu = platform.processor() or platform.machine()
    print(f"Machine: {cpu}, {os.cpu_count()} cores; {args.log.name}: {len(scans)} scans")
    print()
    print("| engine | AUC mean ± std | worst split | per split | s per split |")
    print("|---|---|---|---|---|")
    hps = []
    for variant in variants:
        config = config_of(variant)
        config = dataclasses.replace(config, resolution=args.resolution, dim=scans[0].dim)
        t = time.perf_counter()
        # learning does not depend on the engine: every variant gets the same
        # hyperparameters per split (printed below)
        report = evaluate_log(
            scans, config, seeds=args.seeds, methods=("online",), fast_online=True
        )
        seconds = time.perf_counter() - t
        a = np.array([r.auc for r in report.results["online"]])
        hps = report.hyperparameters
        print(
            f"| {variant or 'lattice (default)'} | {a.mean():.4f} ± {a.std():.4f} | "
            f"{a.min():.4f} | {', '.join(f'{x:.4f}' for x in a)} | {seconds / len(a):.0f} |",
            flush=True,
        )
    print()
    for seed, hp in enumerate(hps):
        print(f"seed {seed}: {hp}")
    return 0


def paper(seeds: int, extra: list[str], exact: bool = True) -> int:
    """AUC of each engine on ``seeds`` simulated data sets of the paper's 2D scene."""
    from octolgp import OnlineMap, learn_hyperparameters
    from octolgp.bench.heldout import auc
    from octolgp.bench.paper2d import paper2d_config
    from octolgp.sim.scenes import simulate_paper2d

    print(f"`{' '.join(['tools/bench_engines.py', *sys.argv[1:]])}`")
    print()
    print("| engine | AUC mean ± std | worst seed | per seed |")
    print("|---|---|---|---|")
    data = [simulate_paper2d(seed=s) for s in range(seeds)]
    base = paper2d_config()
    hps = [learn_hyperparameters(d.scans, base) for d in data]
    for variant in ["", *(["online.engine=exact"] if exact else []), *extra]:
        aucs = []
        for d, hp in zip(data, hps, strict=True):
            config = config_of(variant)
            config = dataclasses.replace(base, online=config.online, hyperparameters=hp)
            m = OnlineMap(config)
            m.insert_batch(d.scans)
            aucs.append(auc(d.truth_labels, m.occupancy(d.truth_points)))
        a = np.array(aucs)
        print(
            f"| {variant or 'lattice (default)'} | {a.mean():.4f} ± {a.std():.4f} | "
            f"{a.min():.4f} | {', '.join(f'{x:.4f}' for x in a)} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
