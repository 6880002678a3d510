"""Screenshots of the Rerun view of a 2D and a 3D map, taken by the real viewer.

Used in BENCHMARKS.md, "The tile view" (``docs/rerun_2d.png``, ``docs/rerun_3d.png``).

Records the Intel log (2D, ``--scans`` scans, the whole log by default) and a simulated 3D
lidar drive down a street (:func:`octolgp.sim.mission.simulate_mission3d`) the way ``octolgp run
--rerun-save`` does, opens each recording in rerun's headless viewer
(``rerun.experimental.ViewerClient.spawn(headless=True)``; on a machine without a GPU it
needs Mesa's software Vulkan driver, ``apt-get install mesa-vulkan-drivers``), moves the time
cursor to the last scan and saves the screenshots:

    .venv/bin/python tools/rerun_screenshots.py            # docs/rerun_2d.png, docs/rerun_3d.png
    .venv/bin/python tools/rerun_screenshots.py --scans 200 --out /tmp

The recordings are kept beside the screenshots with ``--keep``.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from octolgp import MapConfig, OnlineConfig, OnlineMap, Scan, load_scans
from octolgp.sinks.rerun import RerunSink, default_blueprint, open_recording

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"


def record(scans: Iterable[Scan], config: MapConfig, rrd: Path, blueprint: Any) -> int:
    """Map the scans with a Rerun recording as ``octolgp run --rerun-save``; the scan count."""
    rec, _ = open_recording("octolgp", save=rrd, blueprint=blueprint)
    n = 0
    with OnlineMap(config, sink=RerunSink(rec, blueprint=False)) as m:
        for scan in scans:  # one iteration per scan
            m.insert_scan(scan)
            n += 1
        m.flush()
    rec.flush()
    rec.disconnect()
    return n


def hit_bounds(scans: Iterable[Scan]) -> tuple[tuple[float, float], tuple[float, float]]:
    """The ranges of x and y holding 99 % of the hits (beams short of max range), + 5 %."""
    hits = []
    for scan in scans:  # one iteration per scan
        rng = np.linalg.norm(scan.points - scan.origin, axis=1)
        far = np.inf if scan.max_range is None else 0.99 * scan.max_range
        hits.append(scan.points[rng < far][::10, :2])
    lo, hi = np.percentile(np.concatenate(hits), [0.5, 99.5], axis=0)
    margin = 0.05 * float(np.max(hi - lo))
    return (lo[0] - margin, hi[0] + margin), (lo[1] - margin, hi[1] + margin)


def intel(rrd: Path, n_scans: int | None) -> int:
    """The Intel log (2D, 0.1 m).

    The view is zoomed on the building, as a user would zoom: free beams reach 80 m out.
    """
    scans = list(load_scans(INTEL))[:n_scans]
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(n_jobs=2))
    return record(scans, config, rrd, default_blueprint(2, bounds=hit_bounds(scans)))


def street(rrd: Path, n_scans: int) -> int:
    """A simulated street of buildings, trees and poles (3D lidar, 0.2 m; hyperparameters learnt)."""
    from octolgp.sim.mission import simulate_mission3d

    sim = simulate_mission3d(float(n_scans), n_azimuth=360, n_elevation=16)
    config = MapConfig(dim=3, resolution=0.2, online=OnlineConfig(n_jobs=2))
    return record((s.downsample(0.2) for s in sim.scans()), config, rrd, default_blueprint(3))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def screenshot(rrd: Path, last_scan: int, png: Path, *, settle: float) -> None:
    """Open a recording in the headless viewer at its last scan and save a screenshot."""
    from rerun.experimental import ViewerClient

    bin_dir = str(Path(sys.executable).parent)  # the venv's `rerun` viewer binary
    os.environ["PATH"] = bin_dir + os.pathsep + os.environ.get("PATH", "")
    viewer = ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True)
    try:
        viewer.open(str(rrd))
        time.sleep(settle)  # let the viewer load the recording
        viewer.set_time("scan", sequence=last_scan)
        time.sleep(settle)  # and draw the last scan's frame
        png.write_bytes(viewer.take_screenshot())
    finally:
        viewer.quit()
    print(f"wrote {png}")


def main() -> int:
    """Record both maps and screenshot them."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--scans", type=int, default=None, help="Intel scans (default: all)")
    parser.add_argument("--street", type=int, default=60, help="3D street scans (1 m apart)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs")
    parser.add_argument("--settle", type=float, default=6.0, help="seconds to let it draw")
    parser.add_argument("--keep", action="store_true", help="keep the .rrd files in --out")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        where = args.out if args.keep else Path(tmp)
        for name in ("2d", "3d"):
            rrd = where / f"rerun_{name}.rrd"
            t0 = time.perf_counter()
            n = intel(rrd, args.scans) if name == "2d" else street(rrd, args.street)
            size = rrd.stat().st_size
            print(
                f"{name}: {n} scans in {time.perf_counter() - t0:.0f} s, recording "
                f"{size / 1e6:.1f} MB ({size / n / 1e3:.1f} kB per scan)"
            )
            screenshot(rrd, n, args.out / f"rerun_{name}.png", settle=args.settle)
    return 0


if __name__ == "__main__":
    sys.exit(main())
