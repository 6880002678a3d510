"""Where the P = threshold level set lies against the true surfaces, per map setting.

Figures: BENCHMARKS.md, "Planning queries (issue #29)", "Why the level set is early".

The lidar room of ``tools/bench_queries.py`` (``simulate_lidar_room(--poses)``, seed 0,
3 held-out poses, each scan ``downsample(0.2)``, 0.2 m, hyperparameters given: length
scale 0.8 m, alpha 5, beta 0), mapped once per variant (``;``-separated
``SECTION.FIELD=VALUE`` settings as ``tools/bench_3d.py --set``, or ``hp.FIELD=VALUE``
for the given hyperparameters, ``learn`` first to learn them from the scans instead;
empty: the defaults). Per variant:

- the held-out beams (``--rays`` of them, onto observed surfaces: the exact hit within
  a voxel of a mapped endpoint) cast at the threshold: the share of hit points within
  one voxel of a box face, and the median signed error along the ray
  (``exact - distance``: positive is early);
- the field along those beams around the exact hit: the median P at ``k`` half voxels
  before it (``-2`` is a voxel in front of the surface);
- held-out AUC on the room's test points (``LidarRoom.heldout_points``, exact labels).

Run from the repository root::

    .venv/bin/python tools/bench_level_set.py "" "training.free_margin=0.0" "hp.beta=-1.0"
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).parent))
from bench_3d import apply_setting
from bench_queries import HP3, surface_distance

from octolgp import MapConfig, OnlineMap
from octolgp.bench.heldout import evaluate
from octolgp.sim.lidar3d import simulate_lidar_room

OFFSETS = (-4, -3, -2, -1, 0, 1)
"""Half voxels from the exact hit along the beam at which the field is read."""


def variant_config(variant: str) -> MapConfig:
    """The room's config with a variant's settings applied."""
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP3)
    if variant.startswith("learn"):  # hyperparameters learnt from the scans, as by default
        config, variant = MapConfig(dim=3, resolution=0.2), variant[len("learn") :]
    for setting in filter(None, (s.strip() for s in variant.split(";"))):  # each setting
        if setting.startswith("hp."):
            name, _, value = setting[3:].partition("=")
            hp = dataclasses.replace(config.hyperparameters, **{name: float(value)})
            config = dataclasses.replace(config, hyperparameters=hp)
        else:
            config = apply_setting(config, setting)
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("variants", nargs="*", default=[""])
    parser.add_argument("--poses", type=int, default=12)
    parser.add_argument("--rays", type=int, default=5000)
    parser.add_argument("--threshold", type=float, default=0.5)
    args = parser.parse_args()
    sim = simulate_lidar_room(args.poses, seed=0, n_heldout=3)
    scans = [s.downsample(0.2) for s in sim.scans()]
    points, labels, _ = sim.heldout_points(voxel=0.2)
    rng = np.random.default_rng(0)
    o, u, t = [], [], []
    for pose in sim.heldout_poses:  # the held-out poses' beams, exact ranges
        r, d = sim.ranges(pose)
        o.append(np.broadcast_to(pose[:3], d.shape))
        u.append(d)
        t.append(r)
    oo, uu, tt = np.concatenate(o), np.concatenate(u), np.concatenate(t)
    ends = np.concatenate([s.points for s in scans])
    gap, _ = cKDTree(ends).query(oo + np.where(np.isfinite(tt), tt, 0.0)[:, None] * uu)
    seen = np.flatnonzero(np.isfinite(tt) & (gap <= 0.2))
    pick = rng.choice(seen, min(args.rays, seen.size), replace=False)
    oo, uu, tt = oo[pick], uu[pick], tt[pick]
    head = " | ".join(f"P at {k / 2:+g} voxel" for k in OFFSETS)
    print(
        f"| variant | within 1 voxel of a face | median early (m) | {head} | AUC | build (s) |\n"
        f"|---|---|---|{'---|' * len(OFFSETS)}---|---|"
    )
    for variant in args.variants:  # one map per variant
        m = OnlineMap(variant_config(variant))
        t0 = time.perf_counter()
        m.insert_scans(scans)
        m.flush()  # learns the hyperparameters now where they are learnt
        m.settle()
        build = time.perf_counter() - t0
        d = m.raycast(oo, uu, sim.max_range, args.threshold, unknown="free")
        hit = np.isfinite(d)
        face = surface_distance(oo[hit] + d[hit, None] * uu[hit], sim.boxes)
        profile = [
            float(np.median(m.occupancy(oo + (tt + 0.1 * k)[:, None] * uu))) for k in OFFSETS
        ]
        score = evaluate(m, points, labels)
        cells = " | ".join(f"{p:.3f}" for p in profile)
        hp = m.hyperparameters
        print(
            f"| {variant or 'defaults'} (l {hp.length_scale:.2f}, α {hp.alpha:.2f}, β {hp.beta:+.2f}) | {np.mean(face <= 0.2):.1%} "
            f"| {np.median(tt[hit] - d[hit]):+.3f} | {cells} | {score['auc']:.4f} | {build:.1f} |"
        )


if __name__ == "__main__":
    main()
