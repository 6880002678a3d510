"""Where the held-out test points that a map leaves unknown lie, split by what could know them.

For each split of ``octolgp eval``'s protocol (the same seeds, held-out runs and test
points, ``--protocol hilbert``), the online map of the training scans is built in one step
(``--fast-online``'s map) and its unknown test points (reading exactly 0.5) are split into:

- *between beams*: inside a sector two adjacent beams of a training scan sweep
  (:func:`octolgp.sweep.beam_sectors` at ``--angle`` degrees, the configured no-return
  range): what the swept-between-beams rule can make known;
- *beyond the no-return cut*: inside such a sector only when no-return beams are whole
  (``training.no_return_range = inf``);
- *beyond every beam*: the rest, space no training beam's free segment reaches.

``--every K`` keeps every K-th beam of each training scan (the test points stay those of
the whole held-out scans): a sparser scanner, whose diverging beams leave gaps that the
sweep rule (``--map-angle``, the map's ``LatticeConfig.sweep_angle``) makes known.

Figures: BENCHMARKS.md, "The field of view between beams". Run from the repository root::

    .venv/bin/python tools/unknown_split.py ../shared/data/radish_2d/orebro-corrected.log.gz
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys

import numpy as np

from octolgp import MapConfig, load_scans
from octolgp.batch.leafmap import build_tiled
from octolgp.bench.heldout import auc, heldout_split, hilbert_points
from octolgp.gp.learning import learn_hyperparameters
from octolgp.mapping.evidence import map_scans
from octolgp.scan import Scan
from octolgp.sweep import beam_sectors


def in_any_sector(scans: list[Scan], config: MapConfig, points: np.ndarray) -> np.ndarray:
    """Whether each point lies in a sector of some scan (the sweep rule, scan by scan)."""
    out = np.zeros(points.shape[0], dtype=bool)
    for scan in scans:  # one iteration per training scan, vectorised over the points
        _, start, width, reach = beam_sectors([scan], config)
        if not start.size:
            continue
        order = np.argsort(start)
        start, width, reach = start[order], width[order], reach[order]
        off = points - scan.origin
        rho = np.hypot(off[:, 0], off[:, 1])
        phi = np.arctan2(off[:, 1], off[:, 0])
        for shift in (0.0, 2.0 * math.pi):  # a sector may cross the angle ±π
            i = np.clip(np.searchsorted(start, phi + shift, side="right") - 1, 0, start.size - 1)
            turn = phi + shift - start[i]
            out |= (turn >= 0) & (turn <= width[i]) & (rho <= reach[i])
    return out


def thin(scan: Scan, every: int) -> Scan:
    """The scan with every ``every``-th beam."""
    if every == 1:
        return scan
    return dataclasses.replace(scan, points=scan.points[::every])


def main(argv: list[str] | None = None) -> int:
    """Print the split per seed and its mean."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", help="2D CARMEN log")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--angle", type=float, default=2.5, help="sweep angle, degrees")
    ap.add_argument("--map-angle", type=float, default=None, help="the map's (default: its own)")
    ap.add_argument("--every", type=int, default=1, help="keep every K-th training beam")
    args = ap.parse_args(argv)
    scans = list(load_scans(args.log))
    config = MapConfig(dim=2).resolve()
    if args.map_angle is not None:
        config = dataclasses.replace(
            config, lattice=dataclasses.replace(config.lattice, sweep_angle=args.map_angle)
        )
    rule = dataclasses.replace(
        config, lattice=dataclasses.replace(config.lattice, sweep_angle=args.angle)
    )
    whole = dataclasses.replace(
        rule, training=dataclasses.replace(rule.training, no_return_range=math.inf)
    )
    print(f"{args.log}: {len(scans)} scans, sweep_angle {config.sweep_angle} in the map")
    rows = []
    for seed in range(args.seeds):
        train_idx, test_idx = heldout_split(len(scans), fraction=0.1, run=40, seed=seed)
        train = [thin(scans[i], args.every) for i in train_idx]
        points, labels = hilbert_points([scans[i] for i in test_idx], np.random.default_rng(seed))
        hp = learn_hyperparameters(map_scans(train[: config.learn_scans], config), config)
        m = build_tiled(train, dataclasses.replace(config, hyperparameters=hp))
        prob = np.asarray(m.occupancy(points))
        m.close()
        unknown = prob == 0.5
        kept = map_scans(train, config)
        between = np.zeros_like(unknown)
        between[unknown] = in_any_sector(kept, rule, points[unknown])
        cut = np.zeros_like(unknown)
        cut[unknown & ~between] = in_any_sector(kept, whole, points[unknown & ~between])
        row = (
            auc(labels, prob),
            unknown.mean(),
            between.mean(),
            cut.mean(),
            (unknown & ~between & ~cut).mean(),
        )
        rows.append(row)
        print(
            f"seed {seed}: AUC {row[0]:.4f}; unknown {row[1]:.4f} = between beams {row[2]:.4f}"
            f" + beyond the no-return cut {row[3]:.4f} + beyond every beam {row[4]:.4f}",
            flush=True,
        )
    mean = np.mean(rows, axis=0)
    print(
        f"mean: AUC {mean[0]:.4f}; unknown {mean[1]:.4f} = between beams {mean[2]:.4f}"
        f" + beyond the no-return cut {mean[3]:.4f} + beyond every beam {mean[4]:.4f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
