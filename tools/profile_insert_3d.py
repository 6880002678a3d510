"""Profile one 3D lidar insert: stage times and the functions that dominate (issue #14).

A simulated street (``simulate_mission3d``, 200 m loop, a 32 x 1024 lidar, 30 m range,
a scan every 5 m), each scan voxel-filtered at 0.2 m, ``MapConfig(dim=3,
resolution=0.2)`` with given hyperparameters. Inserts scan 1, then profiles scan 2
with cProfile and prints the stage times and the top functions by own time.
Figures: ``docs/design-realtime-3d.md``.

Run from the repository root::

    .venv/bin/python tools/profile_insert_3d.py
"""

from __future__ import annotations

import cProfile
import io
import pstats

import numpy as np

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.sim.mission import simulate_mission3d


def main() -> None:
    mission = simulate_mission3d(200.0, n_azimuth=1024, n_elevation=32, max_range=30.0, spacing=5.0)
    scans = [mission.scan(i).downsample(0.2) for i in range(2)]
    print("beams after the 0.2 m filter:", [len(s) for s in scans])
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp))
    profile = cProfile.Profile()
    for k, scan in enumerate(scans, start=1):
        if k == 2:
            profile.enable()
        u = m.insert_scan(scan)
        profile.disable()
        stages = {name: round(sec, 2) for name, sec in u.stages.items()}
        print(
            f"scan {k}: {u.seconds:.2f} s {stages}, touched {u.touched_leaves}, "
            f"refit {u.refit_leaves}, new items {u.new_items}"
        )
    out = io.StringIO()
    pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(15)
    print(out.getvalue())
    items = np.array([leaf.n_items for _, leaf in m.leaves()])
    print(
        f"items per leaf: median {np.median(items):.0f}, p90 {np.percentile(items, 90):.0f}, "
        f"max {items.max()}"
    )


if __name__ == "__main__":
    main()
