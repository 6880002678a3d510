"""What a map says about space it never saw: the no-return range and honest unknown, on real logs.

Figures: BENCHMARKS.md, "Honest unknown and the free range".

Per log (Intel, shipped; FR079 from ``../shared/data`` when present) and setting (how far
a no-return beam is free, ``TrainingConfig.no_return_range``; how far the GP fills,
``LatticeConfig.fill_voxels``; the widest angle between two beams whose sector counts as
seen, ``LatticeConfig.sweep_angle``, 0 in the rows from before it; the rest the default
config, hyperparameters learnt as a user gets them), the whole log is mapped and the
table gives:

- the map's extent (the box of its voxels, as ``octolgp export`` draws it) and its cells
  free / unknown / occupied at nav2's thresholds (P <= 0.25, P >= 0.65; a cell holding no
  voxel is unknown), as the nav2 PGM has them;
- *unseen*: the cells inside the box of the log's returns (the building) that no beam
  crossed or ended in (every beam whole, whatever the setting); the share of them the map
  reads unknown (exactly 0.5) and free (P <= 0.25) at their centres: a planner told
  "free" there drives into space nobody looked at; and the same for the *deep* unseen
  cells, more than 3 voxels from every seen one (rooms and courtyards no beam entered,
  not the gaps between rays, which the GP is meant to fill);
- *free outside*: cells outside the building's box the map reads free (the no-return
  beams' disc);
- the seconds to map the log.

    .venv/bin/python tools/bench_unknown.py
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from octolgp import LatticeConfig, MapConfig, OnlineMap, Scan, TrainingConfig, load_scans
from octolgp.geometry.keys import key_to_coord
from octolgp.observations import observe

ROOT = Path(__file__).resolve().parents[1]
LOGS = {
    "intel": ROOT / "data" / "intel_lab" / "intel-corrected.log.gz",
    "fr079": ROOT.parent / "shared" / "data" / "fr079" / "freiburg-079-corrected.log.gz",
}
SETTINGS = [
    (math.inf, -1, 0.0),
    (10.0, -1, 0.0),
    (math.inf, 2, 0.0),
    (10.0, 2, 0.0),
    (10.0, 1, 0.0),
    (10.0, 2, 2.5),
]


def cells(points: np.ndarray, res: float) -> np.ndarray:
    """Integer cell indices of points, (n, 2)."""
    return np.floor(points / res).astype(np.int64)


def measure(
    scans: list[Scan], no_return: float, fill: int, res: float, sweep: float = 0.0
) -> dict[str, float]:
    """Map the scans with one setting; the figures of the module's docstring."""
    config = MapConfig(
        dim=2,
        resolution=res,
        training=TrainingConfig(no_return_range=no_return),
        lattice=LatticeConfig(fill_voxels=fill, sweep_angle=sweep),
    )
    t = time.perf_counter()
    m = OnlineMap(config)
    m.insert_scans(scans)
    centres, prob = m.voxels()
    seconds = time.perf_counter() - t
    lo, hi = cells(centres, res).min(0), cells(centres, res).max(0) + 1
    shape = tuple((hi - lo).tolist())
    raster = np.full(shape, np.nan)
    at = cells(centres, res) - lo
    raster[at[:, 0], at[:, 1]] = prob
    free = np.nansum(raster <= 0.25)
    occupied = np.nansum(raster >= 0.65)
    total = raster.size
    # the building: the box of every return; its cells no beam saw (every beam whole)
    whole = dataclasses.replace(config, training=TrainingConfig(no_return_range=math.inf))
    obs = observe(scans, whole)
    seen = {tuple(k) for k in cells(key_to_coord(obs.keys, res, config.tree_depth), res).tolist()}
    returns = np.concatenate(
        [
            s.points[np.linalg.norm(s.points - s.origin, axis=1) < s.max_range * (1 - 1e-9)]
            for s in scans
            if s.max_range is not None
        ]
    )
    blo, bhi = cells(returns, res).min(0), cells(returns, res).max(0) + 1
    gx, gy = np.meshgrid(np.arange(blo[0], bhi[0]), np.arange(blo[1], bhi[1]), indexing="ij")
    box_cells = np.c_[gx.ravel(), gy.ravel()]
    unseen = np.array([tuple(c) not in seen for c in box_cells.tolist()])  # building-sized
    p_unseen = m.occupancy((box_cells[unseen] + 0.5) * res)
    # deep: more than 3 voxels from every seen cell (rooms, courtyards; not ray gaps)
    depth = ndimage.distance_transform_edt(unseen.reshape(gx.shape))
    deep = depth.ravel()[unseen] > 3.0
    p_deep = p_unseen[deep]
    inside = np.zeros(shape, dtype=bool)
    a, b = np.maximum(blo - lo, 0), np.minimum(bhi - lo, np.array(shape))
    inside[a[0] : b[0], a[1] : b[1]] = True
    free_outside = int(np.sum((raster <= 0.25) & ~inside))
    m.close()
    return {
        "extent_m": f"{shape[0] * res:.0f} x {shape[1] * res:.0f}",
        "cells": total,
        "free": int(free),
        "unknown": int(total - free - occupied),
        "occupied": int(occupied),
        "unseen": int(unseen.sum()),
        "unseen_unknown": float(np.mean(p_unseen == 0.5)),
        "unseen_free": float(np.mean(p_unseen <= 0.25)),
        "deep": int(deep.sum()),
        "deep_unknown": float(np.mean(p_deep == 0.5)) if p_deep.size else float("nan"),
        "deep_free": float(np.mean(p_deep <= 0.25)) if p_deep.size else float("nan"),
        "free_outside": free_outside,
        "seconds": seconds,
    }


def main() -> int:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="intel,fr079")
    ap.add_argument("--limit", type=int, default=None, help="first N scans of each log")
    args = ap.parse_args()
    print(
        "| log | no-return range m | fill voxels | sweep ° | extent m | cells | free | unknown | "
        "occupied | "
        "unseen cells in the building | of them unknown | of them free | deep unseen | of them "
        "unknown | of them free | free cells outside the building | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.logs.split(","):
        path = LOGS[name]
        if not path.exists():
            print(f"{name} skipped: {path} is absent (../shared/data is not part of a clone)")
            continue
        scans = list(load_scans(path))[: args.limit]
        for no_return, fill, sweep in SETTINGS:
            r = measure(scans, no_return, fill, 0.1, sweep)
            print(
                f"| {name} | {no_return:g} | {fill} | {sweep:g} | {r['extent_m']} | {r['cells']:,} | "
                f"{r['free']:,} | {r['unknown']:,} | {r['occupied']:,} | {r['unseen']:,} | "
                f"{r['unseen_unknown']:.3f} | {r['unseen_free']:.3f} | {r['deep']:,} | "
                f"{r['deep_unknown']:.3f} | {r['deep_free']:.3f} | {r['free_outside']:,} | "
                f"{r['seconds']:.1f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
