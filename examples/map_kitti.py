"""Map a KITTI odometry sequence with the online mapper, scan by scan, and export it.

    python examples/map_kitti.py                                   # the bundled fixture
    python examples/map_kitti.py /data/kitti/dataset/sequences/00 --limit 200 --voxel 0.3
    python examples/map_kitti.py SEQ --poses my_poses.txt --out kitti_out

The sequence is read with :func:`octolgp.io.read_kitti` (``velodyne/*.bin`` posed by the
ground truth ``poses/NN.txt`` beside ``sequences/``, or ``--poses``) in the Velodyne's frame at
frame 0, so z is up. Each scan is thinned to one point per ``--voxel`` cube (a KITTI scan holds
about 120,000 points) and inserted into an :class:`~octolgp.OnlineMap`, which learns its
hyperparameters on the first ``--learn-scans`` scans. Outputs, in ``--out``:

- ``kitti.octolgp``: the map file (``octolgp query``/``export`` read it);
- ``kitti.pcd``: the occupied voxel centres (P > 0.7) with their probability;
- ``kitti.pgm`` and ``kitti.yaml``: a nav2 map, the 2.5D projection of the voxels between
  ``--z-range`` (metres, relative to the sensor; the default spans the road, 1.73 m below
  the sensor, to just above the car's roof).
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

from tqdm import tqdm

from octolgp import MapConfig, OnlineConfig, OnlineMap
from octolgp.export.nav2 import write_nav2_map
from octolgp.export.pcd import write_pcd
from octolgp.io import read_kitti

FIXTURE = Path(__file__).resolve().parent.parent / "tests" / "data" / "kitti" / "sequences" / "00"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", nargs="?", type=Path, default=FIXTURE, help=".../sequences/NN")
    parser.add_argument("--poses", type=Path, default=None, help="poses file (default: found)")
    parser.add_argument("--out", type=Path, default=Path("kitti_out"), help="output folder")
    parser.add_argument("--resolution", type=float, default=0.4, help="voxel edge, metres")
    parser.add_argument("--voxel", type=float, default=0.2, help="thin scans to this, metres")
    parser.add_argument("--limit", type=int, default=None, help="first N scans only")
    parser.add_argument("--learn-scans", type=int, default=3, help="scans to learn on")
    parser.add_argument("--z-range", type=float, nargs=2, default=(-1.9, 0.5))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    # 1. the scans, streamed: ground-truth poses, Velodyne frame 0 as the world (z up)
    scans = read_kitti(args.sequence, poses=args.poses, world="velodyne")
    config = MapConfig(
        dim=3, resolution=args.resolution, online=OnlineConfig(learn_scans=args.learn_scans)
    )
    target = args.out / "kitti.octolgp"
    for suffix in ("", "-wal", "-shm"):
        Path(f"{target}{suffix}").unlink(missing_ok=True)
    t0 = time.perf_counter()
    # 2. the online map, one scan at a time, persisted after each
    with OnlineMap(config, path=target) as m:
        n = 0
        for scan in tqdm(itertools.islice(scans, args.limit), desc="mapping", unit="scan"):
            m.insert_scan(scan.downsample(args.voxel))
            n += 1
        centres, prob = m.voxels()
    seconds = time.perf_counter() - t0
    # 3. exports: occupied voxels as PCD, the 2.5D projection as a nav2 map
    occupied = prob > 0.7
    write_pcd(args.out / "kitti.pcd", centres[occupied], prob[occupied])
    yaml = write_nav2_map(
        args.out / "kitti.pgm", centres, prob, args.resolution, z_range=tuple(args.z_range)
    )
    print(
        f"{args.sequence}: {n} scans in {seconds:.1f} s ({n / seconds:.2f} scans/s), "
        f"{centres.shape[0]} voxels, {int(occupied.sum())} occupied -> {target}, "
        f"{args.out / 'kitti.pcd'}, {yaml}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
