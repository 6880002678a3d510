"""What the ROS 2 node's publishing costs, and how long it holds up scans, measured without ROS.

Figures: BENCHMARKS.md, "ROS 2 node".

The node (``examples/ros2/octolgp_ros``) publishes on its own timer under a multi-threaded
executor; a scan waits for it only while ``OnlineMap.voxels()`` holds the map's lock. This
script replays a log through an :class:`octolgp.OnlineMap` writing a map file, as the node
does, and every ``--every`` scans runs the node's publishing path on the map as it is:

- ``settle``: the leaf fits the inserts deferred (``OnlineConfig.defer_fit``), which the
  node's ``OnlineMap.voxels()`` call runs first; measured on its own (``OnlineMap.settle``),
  since any read pays it and it is the map's work, not publishing;
- ``voxels``: then ``OnlineMap.voxels()``, the copy of the map's values; with ``settle`` the
  part that holds the map (and so the scans);
- ``grid``: :func:`~octolgp.export.ros_out.map_grid` and :class:`~octolgp.export.ros_out.GridSync`
  (a full grid or the changed tiles), plus the ``array.array`` copy a message's data needs;
- 3D only: ``octomap`` (:func:`~octolgp.export.ros_out.octomap_binary`) and ``cubes``
  (:func:`~octolgp.export.ros_out.occupied_cubes`; the node then makes one ``Point`` and one
  ``ColorRGBA`` per cube, which needs ``rclpy`` and is not measured here).

It prints the median and largest time of each stage, the median ``insert_scan``, and the
bytes sent as full grids and as updates against the bytes of publishing every grid in full.

Usage::

    python tools/bench_ros_publish.py ../shared/data/intel_lab/intel-corrected.log.gz --every 10
    python tools/bench_ros_publish.py room --every 2 --resolution 0.2 --downsample 0.2
"""

from __future__ import annotations

import argparse
import array
import dataclasses
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from octolgp import MapConfig, OnlineMap, load_scans
from octolgp.export.ros_out import GridMessage, GridSync, map_grid, occupied_cubes, octomap_binary
from octolgp.sim.lidar3d import simulate_lidar_room


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path, help="a scan log, or 'room' for the simulated lidar room")
    parser.add_argument("--poses", type=int, default=24, help="room: lidar poses on the loop")
    parser.add_argument("--every", type=int, default=10, help="scans between publishes")
    parser.add_argument("--resolution", type=float, default=None)
    parser.add_argument("--downsample", type=float, default=0.0)
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--full-period", type=int, default=10, help="publishes between full grids")
    args = parser.parse_args()

    if str(args.log) == "room":  # tools/bench_3d.py's room: a 32 x 1024 lidar, 20 x 20 x 5 m
        scans = simulate_lidar_room(args.poses).scans()[: args.limit]
    else:
        scans = list(load_scans(args.log))[: args.limit]
    if args.downsample > 0:
        scans = [s.downsample(args.downsample) for s in scans]
    dim = scans[0].points.shape[1]
    config = MapConfig(dim=dim)
    if args.resolution:
        config = dataclasses.replace(config, resolution=args.resolution)
    # the node's GridSync runs on seconds; here one publish is one second
    sync = GridSync(full_period=float(args.full_period))
    times: dict[str, list[float]] = {"insert": [], "settle": [], "voxels": [], "grid": []}
    if dim == 3:
        times.update(octomap=[], cubes=[])
    sent = {"full": 0, "updates": 0, "all_full": 0}
    last = None
    with tempfile.TemporaryDirectory() as tmp:
        m = OnlineMap(config, path=Path(tmp) / "map.octolgp")
        with m:
            for i, scan in enumerate(scans, start=1):
                t = time.perf_counter()
                update = m.insert_scan(scan)
                if not update.buffered:
                    times["insert"].append(time.perf_counter() - t)
                if (i % args.every and i != len(scans)) or m.provisional:
                    continue  # the node publishes nothing while the map learns
                t = time.perf_counter()
                m.settle()
                settled = time.perf_counter() - t
                t = time.perf_counter()
                centres, prob = m.voxels()
                if not centres.shape[0]:
                    continue
                times["settle"].append(settled)
                times["voxels"].append(time.perf_counter() - t)
                t = time.perf_counter()
                grid = map_grid(centres, prob, m.config.resolution)
                out = sync.next(grid, now=float(i // args.every))
                if isinstance(out, GridMessage):
                    sent["full"] += len(array.array("b", out.data.tobytes()))
                else:
                    sent["updates"] += sum(len(array.array("b", u.data.tobytes())) for u in out)
                times["grid"].append(time.perf_counter() - t)
                sent["all_full"] += grid.data.size
                if dim == 3:
                    t = time.perf_counter()
                    tree = octomap_binary(centres, prob, m.config.resolution, m.config.tree_depth)
                    times["octomap"].append(time.perf_counter() - t)
                    t = time.perf_counter()
                    cubes = occupied_cubes(centres, prob, m.config.resolution)
                    times["cubes"].append(time.perf_counter() - t)
                last = (centres.shape[0], grid.data.shape, m.config.resolution)
                if dim == 3:
                    last += (len(tree.data), cubes.points.shape[0])

    print(f"# {args.log.name}: {len(scans)} scans, {dim}D, publish every {args.every} scans")
    print(f"# {platform.processor() or platform.machine()}, {platform.python_version()}")
    print(f"# last publish: {last}")
    for stage, values in times.items():
        if not values:
            continue
        v = np.array(values) * 1e3
        print(
            f"{stage:8s} n={v.size:4d} median {np.median(v):7.1f} ms  "
            f"p90 {np.percentile(v, 90):7.1f} ms  max {v.max():7.1f} ms"
        )
    full, upd, every = sent["full"], sent["updates"], sent["all_full"]
    print(
        f"grid bytes: {full} full + {upd} updates = {full + upd} "
        f"({(full + upd) / every:.1%} of {every} publishing every grid in full)"
    )


if __name__ == "__main__":
    main()
