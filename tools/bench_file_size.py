"""Bytes a map file holds per scan and per observed voxel: leaves, journal, checkpoints.

Figures: BENCHMARKS.md, "Map file size".

Scenes (the default config, each map written with a path):

- ``street64``: the simulated street, a 64 x 1024 lidar (-24.9°..2°) to 80 m with 2 cm
  range noise, ``--scans`` scans 1 m apart from 100 m along the route, each through
  ``Scan.downsample(0.2)`` (the car-lidar case: about 19,000 beams a scan); 0.2 m voxels,
  hyperparameters given (length scale 0.8 m) so that every scan is mapped;
- ``intel``: the first ``--intel-scans`` scans of the Intel log the repository ships
  (``data/intel_lab``); 0.1 m, hyperparameters learnt as a user gets them (on the
  first 40 scans).

Per scene and journal window (the default ``OnlineConfig.journal_scans``, and with
``--window N`` that too) the table gives, after the last scan: the file's bytes (after
closing: the write-ahead log folded in; SQLite reuses the pages of dropped rows rather
than shrinking the file), the leaf records' bytes per observed voxel (a voxel some scan
saw, counted once, in its own leaf) and the journal's per scan, beside what the same
leaves and scans take in the encoding of file version 4 (every voxel value stored, the
evidence and the journal in float64), the checkpoint records, the record bytes the file
gained per scan over the second half of the run, and the median insert time after the
learning step.

    .venv/bin/python tools/bench_file_size.py --scans 40 --window 10
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sqlite3
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from octolgp import Hyperparameters, MapConfig, OnlineMap, Scan, load_scans
from octolgp.engines import engine_for
from octolgp.engines.lattice import LatticeEvidence
from octolgp.mapping.grid import LeafGrid
from octolgp.persist.mapfile import MapFile
from octolgp.sim.mission import simulate_car_street

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"  # shipped with the repository
HP3 = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
_V4_HEADER = 40  # record 4: magic, version, dim, values, pruned, refits, touched


def street_scans(n: int) -> list[Scan]:
    """The 64-ring street, filtered at 0.2 m."""
    mission = simulate_car_street(range_noise=0.02)
    return [mission.scan(100 + k).downsample(0.2) for k in range(n)]


def intel_scans(n: int) -> list[Scan]:
    """The first ``n`` scans of the Intel log."""
    return list(itertools.islice(load_scans(INTEL), n))


def v4_bytes(path: Path) -> tuple[int, int]:
    """Bytes of the file's leaves and journal in the encoding of file version 4."""
    f = MapFile.open(path, read_only=True)
    try:
        engine = engine_for(f.header.config)
        grid = LeafGrid.from_config(f.header.config)
        leaves = 0
        for key in f.header.leaf_keys:  # one leaf per iteration
            ev = f.read_leaf(key).evidence
            voxels = grid.voxels_per_leaf
            leaves += _V4_HEADER + 8 * grid.dim + 12 * voxels + len(engine.encode(ev)) + 4
        journal = sum(8 * s.dim + 24 * len(s) for s in f.scans(f.journal_start))
    finally:
        f.close()
    return leaves, journal


def observed_voxels(path: Path) -> int:
    """Voxels with a count in their own leaf (each observed voxel once)."""
    f = MapFile.open(path, read_only=True)
    try:
        grid = LeafGrid.from_config(f.header.config)
        side, halo, d = grid.side, grid.halo_voxels, grid.dim
        box = side + 2 * halo
        own = np.zeros((box,) * d, dtype=bool)
        own[(slice(halo, halo + side),) * d] = True
        own = own.ravel(order="F")
        total = 0
        for key in f.header.leaf_keys:  # one leaf per iteration
            ev = f.read_leaf(key).evidence
            if isinstance(ev, LatticeEvidence) and ev.counts.shape[1] == own.size:
                total += int(np.count_nonzero((ev.counts.sum(axis=0) > 0) & own))
    finally:
        f.close()
    return total


def table_bytes(path: Path) -> dict[str, int]:
    """Payload bytes per table (records, not SQLite pages)."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        leaves = con.execute("SELECT COALESCE(SUM(LENGTH(data)), 0) FROM leaves").fetchone()[0]
        journal = con.execute(
            "SELECT COALESCE(SUM(LENGTH(points) + LENGTH(origin)), 0), COUNT(*) FROM scans"
        ).fetchone()
        kept = con.execute(
            "SELECT COALESCE(SUM(LENGTH(data)), 0) FROM checkpoint_leaves"
        ).fetchone()[0]
    finally:
        con.close()
    return {"leaves": leaves, "journal": journal[0], "journaled": journal[1], "kept": kept}


def payload_bytes(sizes: dict[str, int]) -> int:
    """Bytes of leaf records, journal and checkpoint records together."""
    return sizes["leaves"] + sizes["journal"] + sizes["kept"]


def run(name: str, scans: list[Scan], config: MapConfig, folder: Path) -> dict[str, float]:
    """Map the scans into a new file; sizes and the median insert time."""
    path = folder / f"{name}.octolgp"
    times, payload = [], []
    with OnlineMap(config, path=path) as m:
        for scan in scans:  # one insert per iteration
            t = time.perf_counter()
            update = m.insert_scan(scan)
            if not update.buffered and "learning" not in update.stages:
                times.append(time.perf_counter() - t)  # inserts after the learning step
            payload.append(payload_bytes(table_bytes(path)))
        n = m.n_scans
    half = len(payload) // 2
    growth = (payload[-1] - payload[half]) / max(len(payload) - 1 - half, 1)
    sizes = table_bytes(path)
    old_leaves, old_journal = v4_bytes(path)
    voxels = observed_voxels(path)
    return {
        "scans": n,
        "file": path.stat().st_size,
        **sizes,
        "v4_leaves": old_leaves,
        "v4_journal": old_journal,
        "voxels": voxels,
        "points": sum(len(s) for s in scans) / len(scans),
        "insert": statistics.median(times[1:] or times) if times else float("nan"),
        "growth": growth,
    }


def main() -> None:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=20, help="street scans (default 20)")
    parser.add_argument(
        "--window", type=int, default=None, help="also OnlineConfig.journal_scans=N"
    )
    parser.add_argument("--intel-scans", type=int, default=200, help="Intel scans (default 200)")
    args = parser.parse_args()
    scenes = {
        "street64": (
            street_scans(args.scans),
            MapConfig(dim=3, resolution=0.2, hyperparameters=HP3),
        ),
        "intel": (intel_scans(args.intel_scans), MapConfig(dim=2, resolution=0.1)),
    }
    print(
        "| scene | journal_scans | scans | points a scan | file MB | leaves B / observed voxel "
        "(v4) | journal kB / scan (v4) | journaled scans | checkpoint kB | record kB added a "
        "scan, second half | median insert s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, (scans, config) in scenes.items():
            windows = [config.online.journal_scans]
            if args.window is not None:
                windows.append(args.window)
            for window in windows:  # the default, then --window
                online = dataclasses.replace(config.online, journal_scans=window)
                cfg = dataclasses.replace(config, online=online)
                r = run(f"{name}-{window}", scans, cfg, Path(tmp))
                per_voxel = r["leaves"] / max(r["voxels"], 1)
                old_voxel = r["v4_leaves"] / max(r["voxels"], 1)
                journal = r["journal"] / r["journaled"] / 1e3 if r["journaled"] else 0.0
                old_journal = r["v4_journal"] / r["journaled"] / 1e3 if r["journaled"] else 0.0
                print(
                    f"| {name} | {window} | {r['scans']} | {r['points']:.0f} | "
                    f"{r['file'] / 1e6:.2f} | {per_voxel:.2f} ({old_voxel:.1f}) | "
                    f"{journal:.1f} ({old_journal:.1f}) | {r['journaled']} | "
                    f"{r['kept'] / 1e3:.0f} | {r['growth'] / 1e3:.1f} | {r['insert']:.3f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
