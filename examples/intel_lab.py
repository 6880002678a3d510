"""Map the bundled Intel lab log (real 2D laser data) online, scan by scan, as ``octolgp run`` does.

Run by ``make demo``. The mapping is ``octolgp run`` itself (``OnlineMap`` with the default
``MapConfig(dim=2, resolution=0.1)``, a progress bar in scans/s, the run streamed to a Rerun
recording); then the map is exported. Writes into ``--out``:

- ``intel_lab.octolgp``: the map file, with its config ``intel_lab.octolgp.toml``;
- ``intel_lab.rrd``: the Rerun recording of the run (``rerun intel_lab.rrd``);
- ``intel_lab.png``: the floor plan of the building (the hits' box), one pixel per cell
  (free light, occupied dark, grey where the map has no information), north up;
- ``intel_lab.bt``: the map as an OctoMap binary tree;
- ``intel_lab.pgm`` and ``intel_lab.yaml``: the map for nav2's ``map_server``.

    python examples/intel_lab.py --out demo [--limit 100] [--no-rerun]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from octolgp.cli import main as octolgp_cli
from octolgp.export.image import floor_plan, write_floor_plan
from octolgp.export.nav2 import write_nav2_map
from octolgp.mapping.online import OnlineMap

LOG = Path(__file__).resolve().parent.parent / "data" / "intel_lab" / "intel-corrected.log.gz"
MARGIN = 1.0  # metres of floor plan around the hits
KEEP = 0.1  # percent of hits at each end of x and y left outside the floor plan (stray returns)


def hits_box(m: OnlineMap) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the lower-left and upper-right cells of the floor plan: the building.

    The box holds the hits of the map's scans but the ``KEEP`` % at each end of each axis
    (returns through windows and doors), grown by ``MARGIN``.
    """
    hits = []
    for scan in m.scans():  # one iteration per journaled scan
        r = np.linalg.norm(scan.points - scan.origin, axis=1)
        hits.append(scan.points[r < (scan.max_range or np.inf)])
    lo, hi = np.percentile(np.concatenate(hits), [KEEP, 100 - KEEP], axis=0)
    res = m.config.resolution
    return (np.floor((lo - MARGIN) / res) + 0.5) * res, (np.floor((hi + MARGIN) / res) + 0.5) * res


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo", help="output folder")
    parser.add_argument("--log", default=str(LOG), help="CARMEN log")
    parser.add_argument("--limit", type=int, default=None, help="stop after N scans")
    parser.add_argument("--no-rerun", action="store_true", help="no Rerun recording")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = {ext: out / f"intel_lab.{ext}" for ext in ("octolgp", "rrd", "png", "bt", "pgm")}

    # Map the log online, scan by scan: the same code path as `octolgp run`.
    run = ["run", args.log, "--out", str(path["octolgp"]), "--overwrite"]
    run += [] if args.limit is None else ["--limit", str(args.limit)]
    run += [] if args.no_rerun else ["--rerun-save", str(path["rrd"])]
    if args.no_rerun:
        path.pop("rrd").unlink(missing_ok=True)  # no stale recording beside the new map
    t0 = time.perf_counter()
    status = octolgp_cli(run)
    if status:
        return status
    seconds = time.perf_counter() - t0

    # Export: floor plan, OctoMap, nav2.
    with OnlineMap.open(path["octolgp"], read_only=True) as m:
        n_scans, res = m.n_scans, m.config.resolution
        image = floor_plan(m.occupancy, *hits_box(m), res)
        write_floor_plan(path["png"], image)
        m.export_octomap(path["bt"])
        yaml = write_nav2_map(path["pgm"], *m.voxels(), res)

    print(f"mapped {n_scans} scans in {seconds:.1f} s ({n_scans / seconds:.2f} scans/s)")
    print(f"floor plan: {image.shape[1]} x {image.shape[0]} cells of {res:g} m")
    for file in [*path.values(), yaml]:
        print(f"  {file} ({file.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
