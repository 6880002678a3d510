"""Per eval split: held-out returns the training never hit, and those it looked through.

Figures: BENCHMARKS.md, "Why splits fail: walls that only the held-out scans hit".

For each split of ``octolgp eval --protocol hilbert``: how much of what the held-out scans
hit the training scans never hit, and how much of that they looked through.

No map is built: it prints, per log and seed, ``novel_fraction`` (held-out returns with no
training return within 0.3 m) and ``seen_free_fraction`` (those of them in voxels a training
free segment crossed, 0.1 m voxels) on the eval's splits and test points::

    python tools/split_novelty.py orebro,belgioioso 5

Logs as in ``tools/quality_variants.py`` (``../shared/data`` is not in a user's clone).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from quality_variants import LOGS

from octolgp import MapConfig, load_scans
from octolgp.bench.evaluation import NOVEL_RADIUS
from octolgp.bench.heldout import heldout_split, hilbert_points, novel_fraction, seen_free_fraction


def main() -> None:
    """Print one line per log: per seed, the novel share and the seen-free share."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("logs", help="comma-separated names: " + ", ".join(LOGS))
    ap.add_argument("seeds", type=int, help="splits (seeds 0 .. N-1)")
    args = ap.parse_args()
    config = MapConfig(dim=2, resolution=0.1)
    for log in args.logs.split(","):
        if not LOGS[log].exists():
            print(f"{log}: {LOGS[log]} is absent (../shared/data is not in a user's clone)")
            continue
        scans = list(load_scans(LOGS[log]))
        cells = []
        for seed in range(args.seeds):
            train_idx, test_idx = heldout_split(len(scans), fraction=0.1, run=40, seed=seed)
            train = [scans[i] for i in train_idx]
            points, labels = hilbert_points(
                [scans[i] for i in test_idx], np.random.default_rng(seed), 0.1
            )
            occupied = points[labels == 1]
            novel = novel_fraction(train, occupied, NOVEL_RADIUS)
            seen = seen_free_fraction(train, occupied, NOVEL_RADIUS, config)
            cells.append(f"seed {seed}: novel {novel:.2f} seen free {seen:.2f}")
        print(f"{log:12s} " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
