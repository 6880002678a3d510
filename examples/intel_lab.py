"""Map the bundled Intel lab log (real 2D laser data) with overlapping local GPs.

Run by ``make demo``. Learns the hyperparameters on a subset, builds the batch
OM_LGP map at 0.1 m and writes ``<out>/intel_lab.png`` (the occupancy probability
on a grid) and the learnt hyperparameters.

    python examples/intel_lab.py --out demo [--every 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from octolgp import MapConfig, build_map, learn_hyperparameters, load_scans

LOG = Path(__file__).resolve().parent.parent / "data" / "intel_lab" / "intel-corrected.log.gz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo", help="output folder")
    parser.add_argument("--log", default=str(LOG), help="CARMEN log")
    parser.add_argument("--every", type=int, default=1, help="use every k-th scan")
    parser.add_argument("--resolution", type=float, default=0.1)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    scans = list(load_scans(args.log))[:: args.every]
    print(f"{args.log}: {len(scans)} scans, {sum(len(s) for s in scans)} beams")
    config = MapConfig(dim=2, resolution=args.resolution)
    t0 = time.perf_counter()
    hp = learn_hyperparameters(scans, config)
    print(f"learnt in {time.perf_counter() - t0:.1f} s: {hp}")
    config = dataclasses.replace(config, hyperparameters=hp)
    t0 = time.perf_counter()
    gmap = build_map(scans, config, method="lgp", n_jobs=2)
    print(f"built {len(gmap.clusters)} local GPs in {time.perf_counter() - t0:.1f} s")

    # Occupancy on a 0.1 m grid over the building (endpoints' 1st-99th percentiles).
    pts = np.concatenate(
        [
            s.points[np.linalg.norm(s.points - s.origin, axis=1) < (s.max_range or np.inf)]
            for s in scans
        ]
    )
    lo, hi = np.percentile(pts, 1, axis=0) - 1.0, np.percentile(pts, 99, axis=0) + 1.0
    xs = np.arange(lo[0], hi[0], args.resolution)
    ys = np.arange(lo[1], hi[1], args.resolution)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    t0 = time.perf_counter()
    prob = gmap.occupancy(grid).reshape(ys.size, xs.size)
    print(f"predicted {grid.shape[0]} points in {time.perf_counter() - t0:.1f} s")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8))
    ax.imshow(
        prob, origin="lower", cmap="gray_r", vmin=0, vmax=1, extent=(lo[0], hi[0], lo[1], hi[1])
    )
    ax.set_title("Intel lab, OM_LGP P(occupied)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(out / "intel_lab.png", dpi=110)
    (out / "hyperparameters.txt").write_text(f"{hp}\n")
    print(f"wrote {out / 'intel_lab.png'}")


if __name__ == "__main__":
    main()
