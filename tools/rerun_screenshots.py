"""Screenshots of the Rerun view of a 2D and a 3D map as ``octolgp run`` opens it.

Used in BENCHMARKS.md, "Rerun streaming" and "The tile view" (``docs/rerun_2d.png``,
``docs/rerun_3d.png``).

Maps the Intel log (2D, ``--scans`` scans, the whole log by default) and a simulated 3D
lidar drive down a street (:func:`octolgp.sim.mission.simulate_mission3d`, written as an npz
scan log, 0.2 m) with ``octolgp run --rerun-save`` itself, so the recordings hold the CLI's
own default blueprint, which the sink bounds on the map as it grows; nothing here zooms.
Each recording is opened in rerun's headless viewer
(``rerun.experimental.ViewerClient.spawn(headless=True)``; on a machine without a GPU it
needs Mesa's software Vulkan driver, ``apt-get install mesa-vulkan-drivers``), the time
cursor is moved to the last scan and the screenshot saved:

    .venv/bin/python tools/rerun_screenshots.py            # docs/rerun_2d.png, docs/rerun_3d.png
    .venv/bin/python tools/rerun_screenshots.py --scans 200 --out /tmp
    .venv/bin/python tools/rerun_screenshots.py --flags="--rerun-colors probability" --suffix _p

The recordings are kept beside the screenshots with ``--keep``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import socket
import sys
import tempfile
import time
from pathlib import Path

from octolgp.cli import main as octolgp
from octolgp.io.npz import write_npz

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"


def run(scans: Path, rrd: Path, flags: list[str]) -> None:
    """``octolgp run SCANS --rerun-save RRD`` with ``flags``, the map beside the recording."""
    out = rrd.with_suffix(".octolgp")
    argv = [str(scans), "--out", str(out), "--rerun-save", str(rrd), "--overwrite", "--quiet"]
    if octolgp(["run", *argv, *flags]) != 0:
        raise SystemExit(f"octolgp run {shlex.join(argv + flags)} failed")


def intel(rrd: Path, n_scans: int | None, flags: list[str]) -> int:
    """The Intel log (2D, 0.1 m, the CLI's defaults); the scans mapped."""
    limit = [] if n_scans is None else ["--limit", str(n_scans)]
    run(INTEL, rrd, [*limit, *flags])
    return n_scans if n_scans is not None else _scan_count(rrd)


def street(rrd: Path, n_scans: int | None, flags: list[str]) -> int:
    """A simulated street of buildings, trees and poles (3D lidar, 0.2 m; hyperparameters learnt)."""
    from octolgp.sim.mission import simulate_mission3d

    sim = simulate_mission3d(float(n_scans or 60), n_azimuth=360, n_elevation=16)
    scans = [s.downsample(0.2) for s in sim.scans()]
    log = rrd.with_suffix(".npz")
    write_npz(log, scans)
    run(log, rrd, ["--resolution", "0.2", *flags])
    return len(scans)


def _scan_count(rrd: Path) -> int:
    from octolgp.io.rrd_read import read_rrd

    return sum(1 for _ in read_rrd(rrd))


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
        viewer.set_time("scan", sequence=last_scan, play_state="paused")
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
    parser.add_argument("--flags", default="", help="more `octolgp run` flags (one string)")
    parser.add_argument("--suffix", default="", help="added to the screenshots' names")
    parser.add_argument("--only", choices=["2d", "3d"], default=None, help="one of the two")
    parser.add_argument("--at", type=int, default=None, help="scan to show (default: the last)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    flags = shlex.split(args.flags)
    with tempfile.TemporaryDirectory() as tmp:
        where = args.out if args.keep else Path(tmp)
        for name in ("2d", "3d") if args.only is None else (args.only,):
            rrd = where / f"rerun_{name}{args.suffix}.rrd"
            t0 = time.perf_counter()
            make = intel if name == "2d" else street
            n = make(rrd, args.scans if name == "2d" else args.street, flags)
            size = rrd.stat().st_size
            print(
                f"{name}: {n} scans in {time.perf_counter() - t0:.0f} s, recording "
                f"{size / 1e6:.1f} MB ({size / n / 1e3:.1f} kB per scan)"
            )
            png = args.out / f"rerun_{name}{args.suffix}.png"
            screenshot(rrd, n if args.at is None else args.at, png, settle=args.settle)
    return 0


if __name__ == "__main__":
    sys.exit(main())
