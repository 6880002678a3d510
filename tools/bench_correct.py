"""Pose corrections: ``OnlineMap.correct_scans`` against a rebuild, on a drifting mission.

Figures: BENCHMARKS.md, "Pose corrections against rebuilding".

A long building (``--length`` m x 12 m: outer walls, rooms of pillars and desks along a
central corridor), a robot with a 360° laser of 180 beams and 10 m range driving the
corridor and back in ``--scans`` poses, ranges exact from the true poses (ray casting,
``octolgp.sim.scenes.ray_box_distance``), so each scan sees only its neighbourhood.
Odometry drifts: each believed pose is the true one moved by a random walk in x, y and
heading (``--drift`` m and rad per scan, standard deviation), so the scans go into the map
where the robot believed it was. A pose graph corrects the map as it goes: every
``--window`` scans it sends the exact corrections of the last window's scans (the drift
undone), and at the end a loop closure corrects every scan still off.

Each correction is timed against a fresh build of the corrected scans inserted so far
(``insert_batch`` of the same scans with the same hyperparameters: what a user without
``correct_scans`` would do), and the final corrected map is compared with a fresh build of
the final scans: max |dP| over every voxel, and AUC against the world's exact geometry
(0.1 m cell centres within 1.5 m of the path's view: 1 inside a box, 0 outside;
interpolated P; unknown = 0.5).

Default config as a user gets it (``MapConfig(dim=2, resolution=0.1)`` with a path:
corrections need the journal; hyperparameters learnt on the first 40 scans).

    .venv/bin/python tools/bench_correct.py
    .venv/bin/python tools/bench_correct.py --scans 300 --window 25
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from octolgp import MapConfig, OnlineMap, Scan
from octolgp.bench.heldout import auc
from octolgp.mapping.correction import transform_scan
from octolgp.sim.scenes import ray_box_distance

RANGE = 10.0
"""Laser range, metres (beams that hit nothing are no-returns)."""


def building(length: float, seed: int) -> np.ndarray:
    """Boxes ``[xmin, ymin, xmax, ymax]``: outer walls, room walls with doors, desks."""
    rng = np.random.default_rng(seed)
    t = 0.2
    boxes = [
        [-t, -6 - t, length + t, -6],  # outer walls
        [-t, 6, length + t, 6 + t],
        [-t, -6, 0, 6],
        [length, -6, length + t, 6],
    ]
    for x in np.arange(0.0, length, 8.0):  # rooms both sides, a 1.2 m door each
        for side in (-1, 1):
            y0, y1 = sorted((side * 1.5, side * 6.0))
            boxes.append([x, y0, x + t, y1])  # partition between rooms
            door = x + 2 + rng.uniform(0, 3)
            wall_y = side * 1.5
            boxes.append([x, wall_y - t / 2, door, wall_y + t / 2])
            boxes.append([door + 1.2, wall_y - t / 2, x + 8, wall_y + t / 2])
            cx, cy = x + rng.uniform(2, 6), side * rng.uniform(3, 5)
            boxes.append([cx - 0.6, cy - 0.4, cx + 0.6, cy + 0.4])  # a desk
    return np.asarray(boxes, dtype=np.float64)


def mission(length: float, n: int, seed: int) -> tuple[list[Scan], np.ndarray, np.ndarray]:
    """The true scans along the corridor and back, and the world's boxes and poses."""
    boxes = building(length, seed)
    s = np.linspace(0.0, 1.0, n)
    x = 2.0 + (length - 4.0) * (1.0 - np.abs(2.0 * s - 1.0))  # there and back
    y = 0.4 * np.sin(2 * np.pi * s * 5)
    heading = np.where(s < 0.5, 0.0, np.pi)
    angles = np.linspace(-np.pi, np.pi, 180, endpoint=False)
    scans = []
    for k in range(n):  # one scan per pose
        phi = heading[k] + angles
        u = np.c_[np.cos(phi), np.sin(phi)]
        r = ray_box_distance(np.tile([x[k], y[k]], (180, 1)), u, boxes)
        r = np.minimum(r, RANGE)
        scans.append(Scan.from_ranges([x[k], y[k], heading[k]], r, angles, max_range=RANGE))
    return scans, boxes, np.c_[x, y]


def labelled_cells(boxes: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """0.1 m cell centres near the path (within the laser's reach) and 1 inside a box."""
    lo, hi = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
    xs, ys = np.arange(lo[0] + 0.05, hi[0], 0.1), np.arange(lo[1] + 0.05, hi[1], 0.1)
    pts = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    near = np.abs(pts[:, None, 0] - path[None, ::10, 0]).min(axis=1) < 4.0
    pts = pts[near]
    inside = (
        (pts[:, None, 0] >= boxes[None, :, 0])
        & (pts[:, None, 0] <= boxes[None, :, 2])
        & (pts[:, None, 1] >= boxes[None, :, 1])
        & (pts[:, None, 1] <= boxes[None, :, 3])
    ).any(axis=1)
    return pts, inside.astype(np.int8)


def pose(x: float, y: float, yaw: float) -> np.ndarray:
    """A 2D rigid transform, 3 x 3."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def drift_transforms(n: int, step: float, seed: int) -> list[np.ndarray]:
    """Accumulated odometry error per scan, as world-frame rigid transforms."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, step, (n, 3)) * [1.0, 1.0, 0.2], axis=0)
    return [pose(*w) for w in walk]


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def max_dp(a: OnlineMap, b: OnlineMap) -> float:
    """Largest |P(a) - P(b)| over the voxels of both maps (NaN where only one knows)."""
    ca, pa = a.voxels()
    cb, pb = b.voxels()
    if ca.shape != cb.shape or not np.array_equal(ca, cb):
        return float("nan")
    return float(np.abs(pa - pb).max()) if pa.size else 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=int, default=200, help="poses on the path (default 200)")
    parser.add_argument("--window", type=int, default=20, help="scans per correction (20)")
    parser.add_argument("--drift", type=float, default=0.01, help="m per scan, std (0.01)")
    parser.add_argument("--length", type=float, default=120.0, help="building length, m (120)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    truth, boxes, path = mission(args.length, args.scans, args.seed)
    cells, labels = labelled_cells(boxes, path)
    drift = drift_transforms(len(truth), args.drift, args.seed)
    believed = [transform_scan(s, D) for s, D in zip(truth, drift, strict=True)]
    fixes = [np.linalg.inv(D) for D in drift]
    print("# Pose corrections against rebuilding (issue #15)")
    print(
        f"Command: `.venv/bin/python tools/bench_correct.py --scans {args.scans} "
        f"--window {args.window} --drift {args.drift} --seed {args.seed}`"
    )
    print(
        f"Machine: {platform.machine()}, {len(__import__('os').sched_getaffinity(0))} cores; "
        f"commit {_commit()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )
    print("octolgp: `OnlineMap(MapConfig(dim=2, resolution=0.1), path=...)`, the user default.")
    print(
        f"Mission: a {args.length:g} x 12 m building, corridor there and back, {len(truth)} scans "
        f"of 180 beams (10 m range), drift {args.drift} m "
        f"(and {0.2 * args.drift} rad) per scan, random walk; final drift "
        f"{np.hypot(*drift[-1][:2, 2]):.2f} m."
    )
    print()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        m = OnlineMap(MapConfig(dim=2, resolution=0.1), path=Path(tmp) / "mission.octolgp")
        current = list(believed)
        insert_s = []
        for k, scan in enumerate(believed, start=1):  # the mission, corrected as it goes
            t = time.perf_counter()
            m.insert_scan(scan)
            insert_s.append(time.perf_counter() - t)
            last = k == len(believed)
            if (k % args.window and not last) or m.hyperparameters is None:
                continue
            lo = 1 if last else max(1, k - args.window + 1)  # the end: a loop closure
            window = {i: fixes[i - 1] for i in range(lo, k + 1)}
            window = {i: T for i, T in window.items() if not np.allclose(T, np.eye(3))}
            if not window:
                continue
            update = m.correct_scans(window)
            for i, T in window.items():
                current[i - 1] = transform_scan(current[i - 1], T)
                fixes[i - 1] = np.eye(3)  # corrected once, exactly
            hp_config = MapConfig(dim=2, resolution=0.1, hyperparameters=m.hyperparameters)
            fresh = OnlineMap(hp_config)
            t = time.perf_counter()
            fresh.insert_batch(current[:k])
            rebuild = time.perf_counter() - t
            rows.append((k, len(window), update, rebuild, "loop closure" if last else "window"))
        final_fresh = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=m.hyperparameters))
        final_fresh.insert_scans(current)
        drifted = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=m.hyperparameters))
        drifted.insert_batch(believed)
        scores = {
            "corrected (correct_scans)": m.occupancy(cells),
            "fresh build of the corrected scans": final_fresh.occupancy(cells),
            "never corrected (drifted)": drifted.occupancy(cells),
        }
        dp = max_dp(m, final_fresh)
        m.close()

    print(
        "| after scan | kind | scans corrected | leaves rebuilt / removed | scans replayed | "
        "correct_scans s | rebuild s | rebuild / correct |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for k, n, u, rebuild, kind in rows:
        print(
            f"| {k} | {kind} | {n} | {u.refit_leaves} / {u.removed_leaves} | "
            f"{int(u.stages.get('replayed_scans', 0))} | {u.seconds:.3f} | {rebuild:.3f} | "
            f"{rebuild / u.seconds:.1f}x |"
        )
    windows = [r for r in rows if r[4] == "window"]
    if windows:
        print(
            f"\nWindow corrections: median {statistics.median(r[2].seconds for r in windows):.3f} s "
            f"against a median rebuild of {statistics.median(r[3] for r in windows):.3f} s; "
            f"insert_scan median {statistics.median(insert_s) * 1e3:.1f} ms."
        )
    print(
        f"\nFinal map against a fresh build of the final scans: max |dP| = {dp:.2e} "
        "over every voxel (the same leaves)."
    )
    print("\n| map | AUC vs the world's cells (unknown = 0.5) |")
    print("|---|---|")
    for name, p in scores.items():
        print(f"| {name} | {auc(labels, np.where(np.isnan(p), 0.5, p)):.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
