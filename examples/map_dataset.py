"""Map one of the real data sets in one step and write a picture of the map.

    python examples/map_dataset.py intel          # bundled with the repo
    python examples/map_dataset.py fr079          # ../shared/data/fr079
    python examples/map_dataset.py 3dtk           # ../shared/data/3dtk_example_scans
    python examples/map_dataset.py octomap-scan   # ../shared/data/octomap_scan
    python examples/map_dataset.py all

Each run maps the scans with :func:`octolgp.tiled.build_tiled` (every leaf fitted once:
the same map as inserting them one by one into an ``OnlineMap``; hyperparameters learnt
on the first 40 scans), saves the map file ``<out>/<name>.octolgp`` and draws
``<out>/<name>.png``: for a 2D log the occupancy image (occupied dark, free light,
unknown grey); for 3D scans the occupied voxels seen from above and from the side,
coloured by height (those with P above ``--threshold``, 0.7). The data sets other than Intel are not shipped with the repo;
the script says so and skips them when ``--data`` does not hold them.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from octolgp import MapConfig, load_scans
from octolgp.batch.leafmap import build_tiled
from octolgp.export.image import write_png

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"

# name -> (path relative to --data, or absolute; resolution m; voxel filter m or None)
DATASETS: dict[str, tuple[Path, float, float | None]] = {
    "intel": (ROOT / "data" / "intel_lab" / "intel-corrected.log.gz", 0.1, None),
    "fr079": (Path("fr079") / "freiburg-079-corrected.log.gz", 0.1, None),
    "3dtk": (Path("3dtk_example_scans"), 0.2, 0.2),
    "octomap-scan": (Path("octomap_scan") / "scan.dat.bz2", 0.2, 0.2),
}


def draw_3d(path: Path, centres: np.ndarray, prob: np.ndarray, title: str) -> None:
    """Occupied voxel centres from above (x-y) and from the side (x-z), coloured by z."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 6))
    top, side = fig.subplots(1, 2)
    order = np.argsort(centres[:, 2])  # draw high voxels last, on top
    c = centres[order]
    for ax, (i, j), name in ((top, (0, 1), "top (x-y)"), (side, (0, 2), "side (x-z)")):
        art = ax.scatter(c[:, i], c[:, j], c=c[:, 2], s=0.3, cmap="viridis", linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(f"{title}: {name}")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)" if j == 1 else "z (m)")
    fig.colorbar(art, ax=side, label="z (m)", shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def map_dataset(
    name: str, data: Path, out: Path, jobs: int, limit: int | None, threshold: float = 0.7
) -> bool:
    """Map one data set; returns False (with a message) when its files are absent."""
    rel, resolution, voxel = DATASETS[name]
    path = rel if rel.is_absolute() else data / rel
    if not path.exists():
        print(f"{name}: {path} is absent (the shared data set is not in this clone); skipped")
        return False
    scans = [
        s.downsample(voxel) if voxel else s
        for s in tqdm(itertools.islice(load_scans(path), limit), desc=f"{name}: reading")
    ]
    n = len(scans)
    config = MapConfig(dim=scans[0].dim, resolution=resolution)
    target = out / f"{name}.octolgp"
    for suffix in ("", "-wal", "-shm"):
        Path(str(target) + suffix).unlink(missing_ok=True)
    t0 = time.perf_counter()
    # every leaf fitted once: the same map as inserting the scans one by one
    with build_tiled(scans, config, path=target, n_jobs=jobs) as m:
        centres, prob = m.voxels()
        seconds = time.perf_counter() - t0
        picture = out / f"{name}.png"
        if config.dim == 2:
            write_png(picture, centres, prob, resolution)
        else:
            # voxels far from any data sit near the prior's P (about 0.55 here), not 0.5:
            # draw only those the map is confident about
            occ = prob > threshold
            draw_3d(picture, centres[occ], prob[occ], name)
        hp = m.hyperparameters
    print(
        f"{name}: {n} scans in {seconds:.1f} s, {centres.shape[0]} voxels "
        f"({int((prob > 0.5).sum())} with P > 0.5) -> {target}, {picture}"
    )
    if hp is not None:
        print(f"  hyperparameters: {dataclasses.asdict(hp)}")
    return True


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", choices=[*DATASETS, "all"])
    parser.add_argument("--data", type=Path, default=SHARED, help="the shared data folder")
    parser.add_argument("--out", type=Path, default=Path("maps"), help="output folder")
    parser.add_argument("--jobs", type=int, default=2, help="threads refitting leaves")
    parser.add_argument("--limit", type=int, default=None, help="first N scans only")
    parser.add_argument("--threshold", type=float, default=0.7, help="3D: draw voxels above")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    names = list(DATASETS) if args.dataset == "all" else [args.dataset]
    done = [
        map_dataset(n, args.data, args.out, args.jobs, args.limit, args.threshold) for n in names
    ]
    return 0 if any(done) else 1


if __name__ == "__main__":
    sys.exit(main())
