"""Benchmark of the online mapper: online vs batch, saturation, speed vs OctoMap.

Figures: BENCHMARKS.md, "Online mapper".

Parts (``--parts``, comma-separated; all by default):

``sim``
    The paper's 2D simulation, ``--seeds`` data sets: AUC against ground truth of
    the online map (scans inserted one by one) and of ``build_map(method="lgp")``
    with the same hyperparameters (learnt once on all scans, as ``bench paper2d``).
``intel``
    The Intel lab log, held-out-scan protocol: 10 % of the scans held out in
    contiguous runs of 40 (seeded), endpoints occupied, one free point per beam
    sampled uniformly up to 0.1 m short of the hit. Online vs batch with the same
    hyperparameters (learnt on the first 10 training scans, as the online map
    does), with the grid baseline and OctoMap beside them.
``replay``
    The Intel log replayed three times over: median ``insert_scan`` time and map
    memory per pass, and OctoMap's median insertion time for the same scans.
``3d-heldout`` (not in the default set)
    3DTK leave one scan out: AUC and time per scan for ``free_voxels`` 1, 2, 3.
``3d``
    The 3DTK scans (``../shared/data/3dtk_example_scans``) at 0.2 m: time per scan
    after a voxel-grid filter, beside OctoMap's time for the same filtered scans.

Run from the repository root::

    .venv/bin/python tools/bench_online.py --out bench_online

The Intel log ships with the repository; the 3DTK scans are read from
``../shared/data`` and the part is skipped with a note when they are absent.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from sklearn.metrics import roc_auc_score

from octolgp import (
    ExactConfig,
    MapConfig,
    OnlineConfig,
    OnlineMap,
    build_map,
    learn_hyperparameters,
    load_scans,
)
from octolgp.bench.heldout import evaluate, heldout_points, heldout_split
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.bench.paper2d import paper2d_config
from octolgp.scan import Scan
from octolgp.sim.scenes import simulate_paper2d

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "data" / "intel_lab" / "intel-corrected.log.gz"
THREEDTK = ROOT.parent / "shared" / "data" / "3dtk_example_scans"


def _online(config: MapConfig, jobs: int) -> OnlineMap:
    return OnlineMap(dataclasses.replace(config, online=OnlineConfig(n_jobs=jobs)))


def part_sim(seeds: int, jobs: int) -> dict[str, object]:
    """Online vs batch AUC on the paper's simulation."""
    rows = []
    for seed in range(seeds):
        data = simulate_paper2d(seed=seed)
        config = paper2d_config()
        hp = learn_hyperparameters(data.scans, config)
        fixed = dataclasses.replace(config, hyperparameters=hp)
        t0 = time.perf_counter()
        batch = build_map(data.scans, fixed, method="lgp")
        t_batch = time.perf_counter() - t0
        online = _online(fixed, jobs)
        t0 = time.perf_counter()
        online.insert_scans(data.scans)
        t_online = time.perf_counter() - t0
        auc_b = roc_auc_score(data.truth_labels, batch.occupancy(data.truth_points))
        auc_o = roc_auc_score(data.truth_labels, online.occupancy(data.truth_points))
        rows.append((seed, auc_b, auc_o, t_batch, t_online))
        online.close()
    print("\n## Online vs batch, paper's 2D simulation (AUC against ground truth)")
    print("| seed | batch LGP | online | online − batch | batch s | online s |")
    print("|---|---|---|---|---|---|")
    for seed, b, o, tb, to in rows:
        print(f"| {seed} | {b:.4f} | {o:.4f} | {o - b:+.4f} | {tb:.2f} | {to:.2f} |")
    diffs = np.array([r[2] - r[1] for r in rows])
    print(f"| mean | | | {diffs.mean():+.4f} (max abs {np.abs(diffs).max():.4f}) | | |")
    return {"rows": rows, "max_abs_diff": float(np.abs(diffs).max())}


def part_intel(jobs: int, seed: int) -> dict[str, object]:
    """Online vs batch (and grid, OctoMap) on held-out Intel scans."""
    scans = list(load_scans(INTEL))
    train_idx, test_idx = heldout_split(len(scans), fraction=0.1, run=40, seed=seed)
    train = [scans[i] for i in train_idx]
    test = [scans[i] for i in test_idx]
    pts, labels = heldout_points(test, np.random.default_rng(seed), free_per_beam=1, short=0.1)
    config = MapConfig(dim=2, resolution=0.1)
    hp = learn_hyperparameters(train[:10], config)
    fixed = dataclasses.replace(config, hyperparameters=hp)
    results: dict[str, dict[str, float | int]] = {}
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    online = _online(fixed, jobs)
    online.insert_scans(train)
    seconds["octolgp online"] = time.perf_counter() - t0
    results["octolgp online"] = evaluate(online, pts, labels)
    online.close()

    t0 = time.perf_counter()
    batch = build_map(train, fixed, method="lgp", n_jobs=jobs)
    seconds["octolgp batch (lgp)"] = time.perf_counter() - t0
    results["octolgp batch (lgp)"] = evaluate(batch, pts, labels)

    t0 = time.perf_counter()
    grid = build_map(train, fixed, method="ogm")
    seconds["grid (ogm)"] = time.perf_counter() - t0
    results["grid (ogm)"] = evaluate(grid, pts, labels)

    if octomap_available():
        ref = OctomapReference(0.1, 2)
        seconds["OctoMap"] = sum(ref.insert_scan(s) for s in train)
        results["OctoMap"] = evaluate(ref, pts, labels)

    print(
        f"\n## Intel lab, held-out scans (seed {seed}): {len(train)} training scans, "
        f"{len(test)} held out, {labels.size} test points ({int(labels.sum())} occupied)"
    )
    print("| method | AUC | unknown fraction | build s |")
    print("|---|---|---|---|")
    for name, r in results.items():
        print(f"| {name} | {r['auc']:.4f} | {r['unknown_fraction']:.3f} | {seconds[name]:.1f} |")
    diff = float(results["octolgp online"]["auc"]) - float(results["octolgp batch (lgp)"]["auc"])
    print(f"online − batch AUC: {diff:+.4f}; hyperparameters {hp}")
    return {"results": results, "seconds": seconds, "diff": diff}


def part_replay(jobs: int, passes: int) -> dict[str, object]:
    """Intel ×3: per-pass median insert time and memory; OctoMap's per-scan time."""
    scans = list(load_scans(INTEL))
    config = MapConfig(dim=2, resolution=0.1)
    hp = learn_hyperparameters(scans[:10], config)
    m = _online(dataclasses.replace(config, hyperparameters=hp), jobs)
    rows = []
    for p in range(passes):
        t0 = time.perf_counter()
        updates = m.insert_scans(scans)
        wall = time.perf_counter() - t0
        sec = np.array([u.seconds for u in updates])
        refit = np.array([u.refit_leaves for u in updates])
        rows.append(
            {
                "pass": p + 1,
                "median_ms": 1e3 * float(np.median(sec)),
                "p90_ms": 1e3 * float(np.percentile(sec, 90)),
                "mean_ms": 1e3 * float(sec.mean()),
                "wall_s": wall,
                "median_refit": float(np.median(refit)),
                "leaves": len(m.store),
                "memory_mb": m.memory_bytes() / 1e6,
            }
        )
    m.close()
    octo_ms = float("nan")
    if octomap_available():
        ref = OctomapReference(0.1, 2)
        octo_ms = 1e3 * float(np.median([ref.insert_scan(s) for s in scans]))
    print(f"\n## Intel lab replayed {passes}× ({len(scans)} scans per pass, 0.1 m, {jobs} threads)")
    print(
        "| pass | median ms | p90 ms | mean ms | pass s | median refit leaves | leaves | memory MB |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['pass']} | {r['median_ms']:.1f} | {r['p90_ms']:.1f} | {r['mean_ms']:.1f} | "
            f"{r['wall_s']:.1f} | {r['median_refit']:.0f} | {r['leaves']} | {r['memory_mb']:.1f} |"
        )
    if passes >= 3:
        t_ratio = rows[2]["median_ms"] / rows[1]["median_ms"]
        m_ratio = rows[2]["memory_mb"] / rows[1]["memory_mb"]
        print(f"pass 3 / pass 2: median time {t_ratio:.2f} (≤ 1.2), memory {m_ratio:.3f} (≤ 1.1)")
    print(
        f"OctoMap median insert per scan: {octo_ms:.2f} ms; octolgp pass 1 / OctoMap: "
        f"{rows[0]['median_ms'] / octo_ms:.1f}×"
    )
    return {"rows": rows, "octomap_median_ms": octo_ms}


def part_3d(jobs: int, voxel: float) -> dict[str, object]:
    """3DTK scans at 0.2 m: octolgp online time per scan vs OctoMap on the same scans."""
    if not THREEDTK.is_dir():
        print(f"\n## 3DTK: skipped, {THREEDTK} is absent (it lives in ../shared/data)")
        return {}
    raw: list[Scan] = list(load_scans(THREEDTK))
    scans = [s.downsample(voxel) for s in raw]
    config = MapConfig(dim=3, resolution=0.2)
    t0 = time.perf_counter()
    hp = learn_hyperparameters(scans[:1], config)
    t_learn = time.perf_counter() - t0
    m = _online(dataclasses.replace(config, hyperparameters=hp), jobs)
    rows = []
    ref = OctomapReference(0.2, 3) if octomap_available() else None
    for i, (r, s) in enumerate(zip(raw, scans, strict=True)):
        u = m.insert_scan(s)
        t_octo = ref.insert_scan(s) if ref is not None else float("nan")
        rows.append(
            (i, len(r), len(s), u.seconds, u.touched_leaves, u.refit_leaves, t_octo, u.stages)
        )
    m.close()
    print(
        f"\n## 3DTK scans at 0.2 m ({jobs} threads): voxel-grid filter {voxel} m, "
        f"hyperparameters learnt on scan 0 in {t_learn:.1f} s: {hp}"
    )
    print("| scan | points | after filter | octolgp s | touched | refit | OctoMap s | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for i, n0, n1, t, tl, rl, to, _ in rows:
        print(f"| {i} | {n0} | {n1} | {t:.2f} | {tl} | {rl} | {to:.3f} | {t / to:.0f}× |")
    stages = {k: float(np.mean([r[7].get(k, 0.0) for r in rows])) for k in rows[0][7]}
    print("mean seconds per stage: " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()))
    return {"rows": [r[:7] for r in rows], "stages": stages}


def part_3d_heldout(jobs: int, voxel: float) -> dict[str, object]:
    """3DTK leave-one-scan-out AUC and time for OnlineConfig.free_voxels 1, 2, 3, and OctoMap."""
    if not THREEDTK.is_dir():
        print(f"\n## 3DTK held out: skipped, {THREEDTK} is absent")
        return {}
    raw: list[Scan] = list(load_scans(THREEDTK))
    scans = [s.downsample(voxel) for s in raw]
    config = MapConfig(dim=3, resolution=0.2)
    hp = learn_hyperparameters(scans[:1], config)
    print("\n## 3DTK, leave one scan out (every 5th held-out test point), 0.2 m")
    print("| held out | method | AUC | unknown fraction | seconds per inserted scan |")
    print("|---|---|---|---|---|")
    rows = []
    for hold in range(len(scans)):
        train = [s for i, s in enumerate(scans) if i != hold]
        pts, labels = heldout_points([raw[hold]], np.random.default_rng(0), free_per_beam=1)
        pts, labels = pts[::5], labels[::5]
        if octomap_available():
            ref = OctomapReference(0.2, 3)
            t = [ref.insert_scan(s) for s in train]
            r = evaluate(ref, pts, labels)
            print(
                f"| {hold} | OctoMap | {r['auc']:.4f} | {r['unknown_fraction']:.3f} | "
                + " / ".join(f"{x:.2f}" for x in t)
                + " |"
            )
        for fv in (1, 2, 3):  # free_voxels thins the exact engine's free pieces
            online = OnlineConfig(n_jobs=jobs, engine="exact")
            config = MapConfig(
                dim=3,
                resolution=0.2,
                hyperparameters=hp,
                online=online,
                exact=ExactConfig(free_voxels=fv),
            )
            m = OnlineMap(config)
            t = [m.insert_scan(s).seconds for s in train]
            r = evaluate(m, pts, labels)
            m.close()
            rows.append((hold, fv, r["auc"], t))
            print(
                f"| {hold} | octolgp exact, free_voxels={fv} | {r['auc']:.4f} | "
                f"{r['unknown_fraction']:.3f} | " + " / ".join(f"{x:.2f}" for x in t) + " |"
            )
    return {"rows": rows}


def main() -> int:
    """Run the chosen parts and print their tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="sim,intel,replay,3d")
    parser.add_argument("--jobs", type=int, default=2, help="threads refitting leaves")
    parser.add_argument("--seeds", type=int, default=5, help="simulated data sets")
    parser.add_argument("--seed", type=int, default=0, help="held-out split seed")
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--voxel", type=float, default=0.2, help="3D voxel-grid filter, m")
    parser.add_argument("--out", default=None, help="write results.json here")
    args = parser.parse_args()
    parts = set(args.parts.split(","))
    print(f"octolgp online benchmark; python {sys.version.split()[0]}; {args.jobs} threads")
    out: dict[str, object] = {}
    if "sim" in parts:
        out["sim"] = part_sim(args.seeds, args.jobs)
    if "intel" in parts:
        out["intel"] = part_intel(args.jobs, args.seed)
    if "replay" in parts:
        out["replay"] = part_replay(args.jobs, args.passes)
    if "3d" in parts:
        out["3d"] = part_3d(args.jobs, args.voxel)
    if "3d-heldout" in parts:
        out["3d-heldout"] = part_3d_heldout(args.jobs, args.voxel)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "results.json").write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
