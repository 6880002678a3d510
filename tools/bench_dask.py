"""Dask build of a mid-size scene vs the local build: same map, and the time of each.

Figures: BENCHMARKS.md, "Dask: 2-worker build of a mid-size scene".

The scene is ``tools/bench_scale.py``'s street (``--length`` metres of loop, a 360 x 16
lidar every metre). The local build fits the leaves on ``--jobs`` threads in this process;
the Dask build runs them as tasks on an embedded ``LocalCluster`` of ``--workers`` worker
processes (one thread each; cluster start-up timed separately). Both maps are then
compared leaf by leaf, voxel by voxel (mean, variance, P: bit for bit).

    .venv/bin/python tools/bench_dask.py --length 27 --workers 2 --jobs 2
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main() -> int:
    from distributed import Client, LocalCluster

    from octolgp import Hyperparameters, MapConfig
    from octolgp.batch.leafmap import build_tiled
    from octolgp.sim.mission import simulate_mission3d

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--length", type=float, default=27.0, help="loop length, metres")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--hp",
        default='{"length_scale": 1.4844, "signal_variance": 4.1149, "noise_variance": 0.0501,'
        ' "alpha": 15.718, "beta": -0.2355}',
        help="hyperparameters (JSON); default: those bench_scale learns",
    )
    args = parser.parse_args()
    mis = simulate_mission3d(
        length=args.length, spacing=1.0, seed=0, n_azimuth=360, n_elevation=16, max_range=30.0
    )
    scans = list(mis.scans())
    config = MapConfig(
        dim=3, resolution=0.2, hyperparameters=Hyperparameters(**json.loads(args.hp))
    )

    t0 = time.perf_counter()
    local = build_tiled(scans, config, n_jobs=args.jobs)
    local_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    with (
        LocalCluster(
            n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster) as client,
    ):
        start_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        remote = build_tiled(scans, config, scheduler=client)
        dask_s = time.perf_counter() - t1

    keys_l = [k for k, _ in local.leaves()]
    keys_r = [k for k, _ in remote.leaves()]
    same = keys_l == keys_r
    voxels = 0
    for k in keys_l if same else []:  # one iteration per leaf
        a, b = local.store.get(k), remote.store.get(k)
        assert a is not None
        assert b is not None
        same &= all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("mean", "var", "prob"))
        voxels += a.prob.size
    items = int(local.build_stats["items"])
    print(f"scene: {len(scans)} scans, {len(keys_l)} leaves, {items:,} leaf items")
    print("| build | seconds | map |")
    print("|---|---|---|")
    print(f"| local, {args.jobs} threads | {local_s:.1f} | reference |")
    print(
        f"| Dask LocalCluster, {args.workers} workers x 1 thread | {dask_s:.1f} "
        f"(+ {start_s:.1f} cluster start) | "
        f"{'identical' if same else 'DIFFERENT'} ({voxels:,} stored voxel values compared) |"
    )
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
