"""Record the Intel lab log to Rerun the way a robot would, then replay it into octolgp.

A robot logs raw ``rerun`` calls, not octolgp's own ``octolgp/scan`` records. For each laser
scan, on a ``frame`` sequence timeline and a ``time`` timestamp timeline, it logs:

- ``world/robot``: ``Transform3D(translation=(x, y, 0), rotation_axis_angle=(z, theta))``, the
  laser pose from the CARMEN ``FLASER`` line (``theta`` is the laser heading);
- ``world/robot/laser``: ``Points2D``, the beam endpoints in the laser frame (x ahead).

The file is then replayed with :func:`octolgp.load_scans`, which picks the points entity,
composes its pose (latest-at) and returns world-frame scans; they are checked against the
log's own scans (Rerun stores float32, so to about 1e-5 m). With ``--map`` an
:class:`~octolgp.OnlineMap` is built from the replay and saved. A recording carries no
no-return threshold, so the map is built with :func:`octolgp.io.read_rrd` and the log's
``max_range``.

    python examples/rerun_robot.py --out rec.rrd [--scans 200] [--map intel.octolgp]

Open ``rec.rrd`` in the viewer with ``rerun rec.rrd``.
"""

from __future__ import annotations

import argparse
import gzip
import math
import time
from collections.abc import Iterator
from itertools import islice
from pathlib import Path

import numpy as np
import rerun as rr

from octolgp import MapConfig, OnlineMap, Scan, load_scans
from octolgp.io import read_rrd

LOG = Path(__file__).resolve().parent.parent / "data" / "intel_lab" / "intel-corrected.log.gz"


def flaser_poses(path: Path) -> Iterator[tuple[float, float, float]]:
    """Laser poses ``(x, y, theta)`` of the ``FLASER`` lines, in file order.

    ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta timestamp host logger_ts``
    (see :mod:`octolgp.io.carmen`, which yields one scan per such line).
    """
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as fh:
        for line in fh:
            tokens = line.split()
            if tokens and tokens[0] == "FLASER":
                n = int(tokens[1])
                x, y, theta = (float(v) for v in tokens[n + 2 : n + 5])
                yield x, y, theta


def record(log: Path, out: Path, count: int) -> list[Scan]:
    """Log the first ``count`` scans of ``log`` to ``out`` with raw rerun calls."""
    scans: list[Scan] = []
    rec = rr.RecordingStream("octolgp_rerun_robot")
    rec.save(out)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    pairs = islice(zip(load_scans(log), flaser_poses(log), strict=True), count)
    for frame, (scan, (x, y, theta)) in enumerate(pairs):
        if not np.allclose(scan.origin, (x, y)):
            raise SystemExit(f"{log}: scan {frame} does not match its FLASER pose")
        c, s = math.cos(theta), math.sin(theta)
        laser_from_world = np.array([[c, s], [-s, c]])  # R(theta)^T
        rec.set_time("frame", sequence=frame)
        if scan.stamp is not None:
            rec.set_time("time", timestamp=scan.stamp)
        rec.log(
            "world/robot",
            rr.Transform3D(
                translation=[x, y, 0.0],
                rotation_axis_angle=rr.RotationAxisAngle(axis=[0, 0, 1], radians=theta),
            ),
        )
        rec.log("world/robot/laser", rr.Points2D((scan.points - scan.origin) @ laser_from_world.T))
        scans.append(scan)
    rec.disconnect()  # writes the footer
    return scans


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="rec.rrd", help="Rerun recording to write")
    parser.add_argument("--log", default=str(LOG), help="CARMEN log")
    parser.add_argument("--scans", type=int, default=200, help="number of scans to log")
    parser.add_argument("--map", help="also build an OnlineMap from the replay, saved here")
    parser.add_argument("--resolution", type=float, default=0.1)
    args = parser.parse_args()
    out = Path(args.out)

    t0 = time.perf_counter()
    scans = record(Path(args.log), out, args.scans)
    beams = sum(len(s) for s in scans)
    print(
        f"logged {len(scans)} scans ({beams} beams) to {out} "
        f"({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s"
    )

    t0 = time.perf_counter()
    replayed = list(load_scans(out))
    print(f"replayed {len(replayed)} scans with load_scans in {time.perf_counter() - t0:.2f} s")
    if len(replayed) != len(scans):
        raise SystemExit(f"replay gave {len(replayed)} scans, logged {len(scans)}")
    error = max(
        max(np.abs(a.points - b.points).max(), np.abs(a.origin - b.origin).max())
        for a, b in zip(replayed, scans, strict=True)
    )
    stamps = max(
        abs((a.stamp or 0.0) - (b.stamp or 0.0)) for a, b in zip(replayed, scans, strict=True)
    )
    print(f"largest difference: {error:.2e} m (float32), stamps {stamps:.1e} s")
    if error > 1e-4:
        raise SystemExit("replayed scans differ from the log")

    if args.map:
        max_range = scans[0].max_range
        t0 = time.perf_counter()
        with OnlineMap(MapConfig(dim=2, resolution=args.resolution)) as omap:
            for scan in read_rrd(out, max_range=max_range):
                omap.insert_scan(scan)
            omap.flush()
            omap.save(args.map)
        print(
            f"built an OnlineMap of {len(scans)} scans (max_range {max_range}) "
            f"in {time.perf_counter() - t0:.1f} s, saved to {args.map}"
        )


if __name__ == "__main__":
    main()
