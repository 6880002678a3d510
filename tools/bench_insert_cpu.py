"""CPU seconds of a 3D ``insert_scan`` on one thread, by stage: an A/B probe for engine changes.

The simulated room of ``tools/bench_3d.py`` (32 x 1024 lidar, 12 scans through
``Scan.downsample(0.2)``), ``MapConfig(dim=3, resolution=0.2)`` with given
hyperparameters (length scale 0.8 m) and ``online.n_jobs=1``; each insert is timed by
``time.thread_time`` (CPU seconds of the calling thread, less sensitive to other
processes than wall clock). Compare two checkouts in one shell, alternating::

    PYTHONPATH=/path/to/a .venv/bin/python tools/bench_insert_cpu.py
    PYTHONPATH=/path/to/b .venv/bin/python tools/bench_insert_cpu.py
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.sim.lidar3d import simulate_lidar_room


def main() -> None:
    """Print the median and mean CPU seconds per insert after the first, and stage means."""
    room = simulate_lidar_room(
        12, seed=0, n_azimuth=1024, n_elevation=32, max_range=30.0, range_noise=0.0, n_heldout=1
    )
    scans = [s.downsample(0.2) for s in room.scans()]
    hp = Hyperparameters(
        length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0, beta=0.0
    )
    config = MapConfig(dim=3, resolution=0.2)
    config = dataclasses.replace(
        config, hyperparameters=hp, online=dataclasses.replace(config.online, n_jobs=1)
    )
    m = OnlineMap(config)
    cpu: list[float] = []
    stages: dict[str, float] = {}
    for scan in scans:
        t = time.thread_time()
        update = m.insert_scan(scan)
        cpu.append(time.thread_time() - t)
        for name, seconds in update.stages.items():
            stages[name] = stages.get(name, 0.0) + seconds / len(scans)
    m.close()
    print(f"octolgp from {octolgp.__file__}")
    print(
        f"CPU s per insert after the first: median {np.median(cpu[1:]):.3f}, "
        f"mean {np.mean(cpu[1:]):.3f}; stage means (wall s): "
        + ", ".join(f"{k} {v:.3f}" for k, v in stages.items())
    )


if __name__ == "__main__":
    main()
