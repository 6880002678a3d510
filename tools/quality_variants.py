"""Held-out AUC of online-map settings on real logs.

Figures: BENCHMARKS.md, "Map quality on every log".

Runs the eval's splits, test points and hyperparameter learning (those of ``octolgp
eval``) for the online map only, built in one step, once per variant, so several settings
share one learning per split. A variant is ``;``-separated ``SECTION.FIELD=VALUE`` settings
(empty: the default config). ``--protocol endpoint`` uses one free point per beam (the
protocol of ``tools/bench_engines.py``)::

    python tools/quality_variants.py orebro,edmonton 5 "" "lattice.free_weight=0.08"
    python tools/quality_variants.py fr079 3 "online.clear_scans=0;lattice.evidence_cap=8"

Logs: ``intel`` (bundled), ``fr079`` and the five of ``../shared/data/radish_2d``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_3d import apply_setting

from octolgp import Hyperparameters, MapConfig, load_scans
from octolgp.batch.leafmap import build_tiled
from octolgp.bench.heldout import auc, heldout_points, heldout_split, hilbert_points
from octolgp.gp.learning import learn_hyperparameters

ROOT = Path(__file__).resolve().parent.parent
LOGS = {
    "intel": ROOT / "data/intel_lab/intel-corrected.log.gz",
    "fr079": ROOT.parent / "shared/data/fr079/freiburg-079-corrected.log.gz",
    **{
        name: ROOT.parent / f"shared/data/radish_2d/{name}-corrected.log.gz"
        for name in ("orebro", "freiburg-101", "edmonton", "belgioioso", "fhw")
    },
}


def main() -> None:
    """Print one row per log and variant: AUC mean ± std, worst split, learnt length scale."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("logs", help="comma-separated names: " + ", ".join(LOGS))
    ap.add_argument("seeds", type=int, help="splits (seeds 0 .. N-1)")
    ap.add_argument("variants", nargs="*", default=[""], help="settings; '' is the default")
    ap.add_argument("--protocol", choices=("hilbert", "endpoint"), default="hilbert")
    args = ap.parse_args()
    variants = args.variants or [""]
    for log in args.logs.split(","):
        if not LOGS[log].exists():
            print(f"{log}: {LOGS[log]} is absent (../shared/data is not in a user's clone)")
            continue
        scans = list(load_scans(LOGS[log]))
        aucs: dict[str, list[float]] = {v: [] for v in variants}
        lengths: dict[str, list[float]] = {v: [] for v in variants}
        for seed in range(args.seeds):
            train_idx, test_idx = heldout_split(len(scans), fraction=0.1, run=40, seed=seed)
            test = [scans[i] for i in test_idx]
            train = [scans[i] for i in train_idx]
            rng = np.random.default_rng(seed)
            if args.protocol == "hilbert":
                points, labels = hilbert_points(test, rng, 0.1)
            else:
                points, labels = heldout_points(test, rng, 1, 0.1)
            learnt: dict[tuple[object, object], Hyperparameters] = {}
            for v in variants:
                config = MapConfig(dim=2, resolution=0.1)
                for setting in filter(None, v.split(";")):
                    config = apply_setting(config, setting)
                key = (config.learning, config.training)
                if key not in learnt:
                    learnt[key] = learn_hyperparameters(train[: config.learn_scans], config)
                hp = learnt[key]
                m = build_tiled(train, dataclasses.replace(config, hyperparameters=hp), n_jobs=2)
                aucs[v].append(auc(labels, np.asarray(m.occupancy(points))))
                lengths[v].append(hp.length_scale)
        for v in variants:
            a = np.array(aucs[v])
            print(
                f"{log:12s} {v or 'default':45s} AUC {a.mean():.4f} ± {a.std():.4f} "
                f"worst {a.min():.4f} l {np.mean(lengths[v]):.2f} ± {np.std(lengths[v]):.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
