"""Held-out AUC of the online map's leaf engines on a log, in one run (issue #14).

For each engine (``lattice``, the default, and ``exact``, the paper's local GP with
integral kernels) and each seed, ``octolgp eval``'s protocol (10 % of the scans held
out in runs of 40, endpoints occupied, points along the beams free), the online map
built in one step (the same map as inserting the scans one by one). Hyperparameters
are learnt once per split on the first ``learn_scans`` training scans and shared by
both engines. Extra variants: ``--variant "online.free_weight=0.5"`` (settings
``SECTION.FIELD=VALUE`` separated by ``;``).

    .venv/bin/python tools/bench_engines.py data/intel_lab/intel-corrected.log.gz --seeds 3
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
    parser.add_argument("log", type=Path)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--variant", action="append", default=[])
    args = parser.parse_args()
    scans = list(load_scans(args.log))
    variants = ["", "online.engine=exact", *args.variant]
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


if __name__ == "__main__":
    raise SystemExit(main())
