"""The DTC leaf engine (``OnlineConfig.inducing_per_axis``) against the exact local GP, 3D.

The street scene of ``tools/profile_insert_3d.py`` (32 x 1024 lidar, 0.2 m filter and
resolution, given hyperparameters), ``--scans`` scans one by one into a map per
engine: median seconds per scan, and on the voxels every map predicts, max |ΔP|
against the exact engine and the AUC of P against the scene's exact geometry
(``Mission3D.truth`` at the voxel centres; voxels no scan reached are not scored).
Figures: ``docs/design-realtime-3d.md``.

Run from the repository root::

    .venv/bin/python tools/bench_inducing.py --scans 3 --engines 0,3,4
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from sklearn.metrics import roc_auc_score

from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.sim.mission import simulate_mission3d


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=3)
    parser.add_argument("--engines", default="0,3,4", help="inducing_per_axis values; 0 exact")
    args = parser.parse_args()
    mission = simulate_mission3d(200.0, n_azimuth=1024, n_elevation=32, max_range=30.0, spacing=5.0)
    scans = [mission.scan(i).downsample(0.2) for i in range(args.scans)]
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    base = MapConfig(dim=3, resolution=0.2, hyperparameters=hp)
    results = {}
    for k in (int(v) for v in args.engines.split(",")):
        config = dataclasses.replace(
            base, online=dataclasses.replace(base.online, inducing_per_axis=k)
        )
        m = OnlineMap(config)
        sec = []
        for s in scans:  # one insert per scan
            t0 = time.perf_counter()
            m.insert_scan(s)
            sec.append(time.perf_counter() - t0)
        centres, prob = m.voxels()
        order = np.lexsort(centres.T[::-1])
        results[k] = (np.array(sec), centres[order], prob[order])
    ref_c, ref_p = results[0][1], results[0][2] if 0 in results else (None, None)
    truth = mission.truth(ref_c) if ref_c is not None else None
    print(f"{args.scans} scans of {[len(s) for s in scans]} beams, 0.2 m, 1 thread")
    print(
        "| engine | median s/scan | max s/scan | voxels | max abs dP vs exact | AUC vs geometry |"
    )
    print("|---|---|---|---|---|---|")
    for k, (sec, c, p) in results.items():
        same = ref_c is not None and c.shape == ref_c.shape and np.array_equal(c, ref_c)
        dp = f"{np.abs(p - ref_p).max():.3f}" if same else "-"
        auc = roc_auc_score(mission.truth(c), p)
        name = "exact" if k == 0 else f"DTC {k}^3 = {k**3}"
        print(
            f"| {name} | {np.median(sec):.2f} | {sec.max():.2f} | {c.shape[0]} | {dp} | {auc:.4f} |"
        )
    del truth


if __name__ == "__main__":
    main()
