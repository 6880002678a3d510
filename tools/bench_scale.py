"""Scale benchmark: time, peak memory and AUC from 10^4 to ~3.7 x 10^6 items.

Figures: BENCHMARKS.md, "Scale" and "The paper-sized batch build".

The scene is :func:`octolgp.mission.simulate_mission3d`: a street loop of buildings
(4-15 m tall), fences, poles and trees on a ground plane, scanned by a simulated
spinning lidar (360 x 16 beams, +-15 deg, 30 m range, 1 cm range noise) every metre.
A size is a loop length: a longer loop is more of the same street, so the work per
item stays the same and time should grow linearly.

For each size, in a fresh child process (so its peak RSS is its own):

- simulate the scans (not timed);
- **octolgp**: :func:`octolgp.tiled.build_tiled` with fixed hyperparameters (learnt
  once on the smallest size; learning is a fixed cost, reported separately) on
  ``--jobs`` threads: training data, leaf assignment, and one fit + prediction of
  every voxel centre of every leaf (the test points);
- **grid**: the log-odds occupancy grid baseline (``build_map(method="ogm")``);
- **AUC** against ground truth: 20 extra noise-free scans taken half-way between
  training scans (never trained on) give test points 5 cm behind each hit (inside the
  surface) and drawn along each beam up to one voxel (0.2 m) before the hit, all
  labelled by the scene's exact geometry (``Mission3D.truth``).

"Training items" counts what the paper counts: one hit plus one free segment per
returning beam, one free segment per no-return beam. "Leaf items" is what the local
GPs actually train on after the per-voxel deduplication and halo overlap.

    .venv/bin/python tools/bench_scale.py --sizes 1e4,3e4,1e5,3e5,1e6,3.7e6 --jobs 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = 0.2
BEAMS = {"n_azimuth": 360, "n_elevation": 16, "max_range": 30.0}
TEST_SCANS = 20


def _mission(length: float):
    from octolgp.sim.mission import simulate_mission3d

    return simulate_mission3d(length=length, spacing=1.0, seed=0, **BEAMS)


def _items(scans: list) -> int:
    """Paper's count: a hit and a free segment per return, a free segment per no-return."""
    total = 0
    for s in scans:
        r = np.linalg.norm(s.points - s.origin, axis=1)
        total += len(s) + int(np.count_nonzero(r < s.max_range * (1 - 1e-9)))
    return total


def child(length: float, jobs: int, hp_json: str, grid: bool) -> dict[str, object]:
    """One size, in this (child) process."""
    from octolgp import MapConfig, build_map
    from octolgp.batch.leafmap import build_tiled
    from octolgp.bench.heldout import auc, heldout_points
    from octolgp.config import Hyperparameters

    mis = _mission(length)
    scans = list(mis.scans())
    n_items = _items(scans)
    # test scans half-way between training scans, spread over the loop
    pick = np.linspace(0, mis.n_scans - 1, min(TEST_SCANS, mis.n_scans)).round().astype(int)
    test = [mis.cast(np.asarray(mis.route(k * mis.spacing + 0.5))[:3]) for k in np.unique(pick)]
    # Occupied test points: 5 cm beyond each (noise-free) hit, inside the surface; free:
    # points drawn along the beams up to one voxel (0.2 m) before the hit. Both labelled
    # by the scene's exact geometry (a point exactly on a surface would be a coin flip).
    pts, lab = heldout_points(
        test, np.random.default_rng(0), free_per_beam=1, short=0.1, resolution=RESOLUTION
    )
    inside = []
    for s in test:
        ray = s.points - s.origin
        dist = np.linalg.norm(ray, axis=1)
        hit = dist < s.max_range * (1 - 1e-9)
        inside.append(s.points[hit] + 0.05 * ray[hit] / dist[hit, None])
    pts = np.concatenate([np.concatenate(inside), pts[lab == 0]])
    labels = mis.truth(pts)
    hp = Hyperparameters(**json.loads(hp_json))
    config = MapConfig(dim=3, resolution=RESOLUTION, hyperparameters=hp)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    m = build_tiled(scans, config, n_jobs=jobs)
    seconds = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    stats = dict(m.build_stats)
    out: dict[str, object] = {
        "length": length,
        "scans": len(scans),
        "items": n_items,
        "seconds": seconds,
        "peak_rss_mb": rss,
        "rss_before_mb": rss0,
        "stats": stats,
        "auc": auc(labels, m.occupancy(pts)),
        "test_points": int(stats["voxels"]),
        "eval_points": int(labels.size),
    }
    m.close()
    if grid:
        t0 = time.perf_counter()
        g = build_map(scans, config, method="ogm")
        out["grid_seconds"] = time.perf_counter() - t0
        out["grid_auc"] = auc(labels, g.occupancy(pts))
    return out


def _learn() -> str:
    """Hyperparameters learnt once, on every third scan of a 120 m loop (40 scans).

    Spread over the street: learnt on the first scans of one spot, the length scale ran
    to 4 m (and 2.4 m on the first 40 scans), far too smooth for 0.2 m voxels.
    """
    from octolgp import MapConfig, learn_hyperparameters

    scans = list(_mission(120.0).scans())[::3]
    hp = learn_hyperparameters(scans, MapConfig(dim=3, resolution=RESOLUTION))
    return json.dumps(dataclasses.asdict(hp))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1e4,3e4,1e5,3e5,1e6,3.7e6", help="training items")
    parser.add_argument("--jobs", type=int, default=2, help="threads fitting leaves")
    parser.add_argument("--no-grid", action="store_true", help="skip the grid baseline")
    parser.add_argument("--out", type=Path, default=Path("bench_out"), help="plot and JSON")
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        length, hp_json, grid = float(args.child[0]), args.child[1], args.child[2] == "1"
        print(json.dumps(child(length, args.jobs, hp_json, grid)))
        return 0

    t0 = time.perf_counter()
    hp_json = _learn()
    learn_s = time.perf_counter() - t0
    per_scan = _items(list(_mission(12.0).scans())) / 12
    rows = []
    for size in [float(s) for s in args.sizes.split(",")]:
        length = max(1.0, round(size / per_scan))
        cmd = [sys.executable, __file__, "--jobs", str(args.jobs), "--child", str(length)]
        cmd += [hp_json, "0" if args.no_grid else "1"]
        res = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if res.returncode != 0:
            print(res.stderr[-3000:], file=sys.stderr)
            return 1
        row = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"size {size:.2g}: {row['items']} items, {row['seconds']:.1f} s, "
            f"{row['peak_rss_mb']:.0f} MB, AUC {row['auc']:.4f}",
            file=sys.stderr,
            flush=True,
        )

    print(f"\nhyperparameters (learnt once in {learn_s:.1f} s): {hp_json}")
    print(
        "| scans | training items | leaf items | leaves | test points (voxels) | "
        "octolgp s | items/s | peak RSS MB | AUC | grid s | grid AUC |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        st = r["stats"]
        print(
            f"| {r['scans']} | {r['items']:,} | {int(st['items']):,} | {int(st['leaves']):,} | "
            f"{r['test_points']:,} | {r['seconds']:.1f} | {r['items'] / r['seconds']:,.0f} | "
            f"{r['peak_rss_mb']:.0f} | {r['auc']:.4f} | "
            f"{r.get('grid_seconds', float('nan')):.1f} | {r.get('grid_auc', float('nan')):.4f} |"
        )
    items = np.array([r["items"] for r in rows], dtype=float)
    secs = np.array([r["seconds"] for r in rows])
    if len(rows) >= 2:
        slope = float(np.polyfit(np.log(items), np.log(secs), 1)[0])
        print(f"\nlog-log slope of time against training items: {slope:.3f}")
        stages = ["training", "assign", "fit", "store"]
        print(
            "stage seconds per size: "
            + "; ".join(
                f"{r['items']:,}: " + ", ".join(f"{s} {r['stats'][s]:.1f}" for s in stages)
                for r in rows
            )
        )
        args.out.mkdir(parents=True, exist_ok=True)
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 4.5))
        ax.loglog(items, secs, "o-", label=f"octolgp (slope {slope:.2f})")
        if "grid_seconds" in rows[0]:
            ax.loglog(items, [r["grid_seconds"] for r in rows], "s--", label="grid (ogm)")
        ref = secs[0] * items / items[0]
        ax.loglog(items, ref, ":", color="0.6", label="linear")
        ax.set_xlabel("training items")
        ax.set_ylabel("build seconds")
        ax.legend()
        ax.set_title("octolgp tiled build: time against size")
        fig.tight_layout()
        fig.savefig(args.out / "scale.png", dpi=120)
        (args.out / "scale.json").write_text(json.dumps(rows, indent=2))
        print(f"wrote {args.out}/scale.png, {args.out}/scale.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
