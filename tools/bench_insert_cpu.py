"""CPU seconds of a 3D ``insert_scan``, by stage: an A/B probe for engine changes.

Scenes (the same as ``tools/bench_3d.py``'s, hyperparameters given, length scale 0.8 m):

- ``room``: the simulated room (32 x 1024 lidar, 12 scans through ``Scan.downsample(0.2)``);
- ``street64``: the simulated street, a 64 x 1024 lidar (-24.9°..2°) to 80 m, 7 scans 1 m
  apart from 100 m along the route, through ``Scan.downsample(0.2)``;
- ``kitti``: the KITTI-format fixture (``tests/data/kitti``, five scans of 16 x 24 beams),
  through ``Scan.downsample(0.2)``, mapped ``--repeats`` times over (a new map each time);
- ``3dtk``: the three real 3DTK scans (``../shared/data/3dtk_example_scans``) through
  ``Scan.downsample(0.2)``, mapped ``--repeats`` times over.

``MapConfig(dim=3, resolution=0.2)`` with ``online.n_jobs`` = ``--threads`` (default 1) and
``lattice.free_evidence`` = ``--free-evidence`` where given,
in memory or, with ``--file``, written to a map file in a temporary folder;
each insert is timed by ``time.thread_time`` (CPU seconds of the calling thread, less
sensitive to other processes than wall clock; with ``--threads 2`` the fitting threads'
CPU is not in it, so read the wall column) and by wall clock. Compare two checkouts in
one shell, alternating::

    PYTHONPATH=/path/to/a .venv/bin/python tools/bench_insert_cpu.py --scene street64
    PYTHONPATH=/path/to/b .venv/bin/python tools/bench_insert_cpu.py --scene street64
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineMap, Scan, load_scans
from octolgp.sim.lidar3d import simulate_lidar_room
from octolgp.sim.mission import simulate_car_street

ROOT = Path(__file__).resolve().parents[1]
DATA = {
    "kitti": ROOT / "tests" / "data" / "kitti" / "sequences" / "00",
    "3dtk": ROOT.parent / "shared" / "data" / "3dtk_example_scans",
}


def scene_scans(scene: str) -> list[Scan]:
    """The filtered scans of a scene."""
    if scene in DATA:
        if not DATA[scene].is_dir():
            raise SystemExit(f"{scene}: {DATA[scene]} is absent")
        return [s.downsample(0.2) for s in load_scans(DATA[scene])]
    if scene == "room":
        room = simulate_lidar_room(
            12, seed=0, n_azimuth=1024, n_elevation=32, max_range=30.0, range_noise=0.0, n_heldout=1
        )
        return [s.downsample(0.2) for s in room.scans()]
    mission = simulate_car_street()
    return [mission.scan(100 + k).downsample(0.2) for k in range(7)]


def main() -> None:
    """Print the median CPU and wall seconds per insert after each map's first, and stage medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("room", "street64", "kitti", "3dtk"), default="room")
    parser.add_argument(
        "--repeats", type=int, default=1, help="map the scans this many times, a new map each"
    )
    parser.add_argument("--threads", type=int, default=1, help="online.n_jobs (default 1)")
    parser.add_argument("--file", action="store_true", help="write the map to a map file")
    parser.add_argument(
        "--free-evidence",
        choices=("looks", "chord"),
        default=None,
        help="lattice.free_evidence (default: the config's default)",
    )
    args = parser.parse_args()
    scans = scene_scans(args.scene)
    hp = Hyperparameters(
        length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0, beta=0.0
    )
    config = MapConfig(dim=3, resolution=0.2)
    if args.free_evidence is not None:
        lattice = dataclasses.replace(config.lattice, free_evidence=args.free_evidence)
        config = dataclasses.replace(config, lattice=lattice)
    config = dataclasses.replace(
        config, hyperparameters=hp, online=dataclasses.replace(config.online, n_jobs=args.threads)
    )
    folder = tempfile.TemporaryDirectory() if args.file else None
    path = None if folder is None else Path(folder.name) / "m.octolgp"
    cpu: list[float] = []
    wall: list[float] = []
    stages: dict[str, list[float]] = {}
    leaves: list[int] = []
    for _ in range(args.repeats):  # a new map each time; its first insert left out
        m = OnlineMap(config, path=path)
        for k, scan in enumerate(scans):
            t, w = time.thread_time(), time.perf_counter()
            update = m.insert_scan(scan)
            if k == 0:
                continue
            cpu.append(time.thread_time() - t)
            wall.append(time.perf_counter() - w)
            leaves.append(update.refit_leaves)
            for name, seconds in update.stages.items():
                stages.setdefault(name, []).append(seconds)
        m.close()
        if path is not None:
            path.unlink()
    if folder is not None:
        folder.cleanup()
    where = "a map file" if args.file else "memory"
    print(
        f"octolgp from {octolgp.__file__}; scene {args.scene}, {args.threads} thread(s), "
        f"the map in {where}"
    )
    print(
        f"after the first insert of each map: CPU s median {np.median(cpu):.4f}, wall s median "
        f"{np.median(wall):.4f}, refitted leaves median {int(np.median(leaves))}; "
        "stage medians (wall s): " + ", ".join(f"{k} {np.median(v):.4f}" for k, v in stages.items())
    )


if __name__ == "__main__":
    main()
