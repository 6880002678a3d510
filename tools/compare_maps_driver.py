"""Driver of ``tools/compare_maps.py``: build the comparison maps with one copy of octolgp.

It is run in a subprocess once per code tree, with ``PYTHONPATH`` set to that tree,
and uses only the public API that every version of the package shares
(``from octolgp import ...`` and the maps' public methods), so it runs unchanged
against a baseline commit and against the restructured working tree. It writes
one ``.npz`` whose keys are ``"<data set>.<map>.<field>"`` plus ``"meta.json"``
(the octolgp file imported, timings, and the traceback of any data set that failed;
the others still run).

Usage (normally called by ``compare_maps.py``)::

    PYTHONPATH=TREE python -P tools/compare_maps_driver.py --tree TREE --repo REPO
        --sim SIM.npz --out RESULT.npz [--intel-scans N] [--datasets intel,sim,3dtk]

``--tree`` is the root that must hold the imported ``octolgp`` (the run fails
otherwise); ``--repo`` is where the input data live (``data/`` and
``tests/data/``), the same for every tree.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import traceback
from collections.abc import Callable
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np

DATASETS = ("intel", "sim", "3dtk")
SIM_METHODS = ("lgp", "gp", "mgp", "ogm")
INTEL_LOG = Path("data/intel_lab/intel-corrected.log.gz")
THREEDTK_DIR = Path("tests/data/3dtk")
GRID_SIDE = 501  # the Intel query grid: GRID_SIDE x GRID_SIDE points over the map's extent

Results = dict[str, np.ndarray]


def _import_octolgp(tree: Path) -> Any:
    """Import octolgp and check that it is the copy under ``tree``."""
    import octolgp

    where = Path(octolgp.__file__).resolve()
    print(f"octolgp imported from {where}", flush=True)
    if not where.is_relative_to(tree.resolve()):
        raise SystemExit(f"driver: octolgp comes from {where}, not from the tree {tree}")
    return octolgp


def _sorted_voxels(m: Any) -> tuple[np.ndarray, np.ndarray]:
    """``m.voxels()`` sorted lexicographically by centre coordinates."""
    centres, prob = m.voxels()
    order = np.lexsort(centres.T[::-1])  # last key is the primary one: x, then y, then z
    centres, prob = centres[order], prob[order]
    if len(centres) > 1 and np.any(np.all(centres[1:] == centres[:-1], axis=1)):
        print("  warning: duplicate voxel centres", flush=True)
    return centres, prob


def _hp_array(hp: Any) -> np.ndarray:
    """The fields of a Hyperparameters dataclass, in declaration order, as float64.

    ``None`` (a map that has not learnt its own yet) gives an empty array.
    """
    if hp is None:
        return np.zeros(0)
    return np.array([float(v) for v in dataclasses.asdict(hp).values()])


def _record_online(res: Results, prefix: str, m: Any) -> None:
    """Voxels (sorted), latent at their centres (not interpolated) and hyperparameters."""
    centres, prob = _sorted_voxels(m)
    mean, var = m.latent(centres, interpolate=False)
    res[f"{prefix}_voxels.centres"] = centres
    res[f"{prefix}_voxels.prob"] = prob
    res[f"{prefix}_voxels.mean"] = mean
    res[f"{prefix}_voxels.var"] = var
    res[f"{prefix}_hp.hyperparameters"] = _hp_array(m.hyperparameters)
    print(f"  {prefix}: {len(centres)} voxels, hyperparameters {m.hyperparameters}", flush=True)


def _online(octolgp: Any, scans: list[Any], config: Any) -> Any:
    """An OnlineMap fed scan by scan, with no query in between, then flushed.

    ``flush()`` learns on the buffered scans when a data set has fewer than
    ``learn_scans`` scans. The baseline learnt at the first read instead (the defect of
    issue #13); both versions have ``flush``, so the two maps are the same call.
    """
    m = octolgp.OnlineMap(config)
    for scan in scans:
        m.insert_scan(scan)
    m.flush()
    return m


def run_intel(octolgp: Any, repo: Path, n_scans: int) -> Results:
    """The first ``n_scans`` of the Intel log, online, 2D at 0.1 m."""
    reader = octolgp.load_scans(repo / INTEL_LOG)
    scans = list(islice(reader, n_scans))
    close = getattr(reader, "close", None)
    if close is not None:
        close()
    print(f"  intel: {len(scans)} scans", flush=True)
    m = _online(octolgp, scans, octolgp.MapConfig(dim=2, resolution=0.1))
    res: Results = {}
    _record_online(res, "intel.online", m)
    # A regular grid over the map's extent; its points fall anywhere in the voxels,
    # so the interpolating queries are exercised.
    centres = res["intel.online_voxels.centres"]
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    axes = [np.linspace(a, b, GRID_SIDE) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    res["intel.online_grid.points"] = grid
    res["intel.online_grid.prob"] = m.occupancy(grid)
    mean, var = m.latent(grid)
    res["intel.online_grid.mean"] = mean
    res["intel.online_grid.var"] = var
    return res


def run_sim(octolgp: Any, sim: Path, gp_scans: int | None, timings: dict[str, float]) -> Results:
    """The paper's 2D simulation: online map, batch maps and hyperparameter learning."""
    scans = list(octolgp.load_scans(sim))
    with np.load(sim) as f:
        truth = np.asarray(f["truth_points"])
    print(f"  sim: {len(scans)} scans, {len(truth)} truth points", flush=True)
    res: Results = {"sim.truth.points": truth}

    def config() -> Any:
        return octolgp.MapConfig(dim=2, resolution=0.1)

    t0 = time.perf_counter()
    m = _online(octolgp, scans, config())
    _record_online(res, "sim.online", m)
    res["sim.online_truth.prob"] = m.occupancy(truth)
    mean, var = m.latent(truth)
    res["sim.online_truth.mean"] = mean
    res["sim.online_truth.var"] = var
    timings["sim/online"] = time.perf_counter() - t0

    for method in SIM_METHODS:
        t0 = time.perf_counter()
        used = scans
        if method == "gp" and gp_scans is not None:
            used = scans[:gp_scans]
            print(f"  sim: gp on the first {len(used)} scans only (--gp-scans)", flush=True)
        b = octolgp.build_map(used, config(), method=method)
        res[f"sim.{method}.prob"] = b.occupancy(truth)
        if hasattr(b, "latent"):
            mean, var = b.latent(truth)
            res[f"sim.{method}.mean"] = mean
            res[f"sim.{method}.var"] = var
        timings[f"sim/{method}"] = time.perf_counter() - t0
        print(f"  sim: {method} {timings[f'sim/{method}']:.1f} s", flush=True)

    t0 = time.perf_counter()
    hp = octolgp.learn_hyperparameters(scans[:40], config())
    res["sim.learn40.hyperparameters"] = _hp_array(hp)
    res["sim.learn40.names"] = np.array(list(dataclasses.asdict(hp)))
    timings["sim/learn40"] = time.perf_counter() - t0
    print(f"  sim: learn_hyperparameters {hp}", flush=True)
    return res


def run_3dtk(octolgp: Any, repo: Path) -> Results:
    """The 3DTK test fixture, online, 3D at 0.2 m."""
    scans = list(octolgp.load_scans(repo / THREEDTK_DIR))
    print(f"  3dtk: {len(scans)} scans", flush=True)
    m = _online(octolgp, scans, octolgp.MapConfig(dim=3, resolution=0.2))
    res: Results = {}
    _record_online(res, "3dtk.online", m)
    return res


def main(argv: list[str] | None = None) -> int:
    """Build the maps of the chosen data sets and save them to ``--out``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tree", type=Path, required=True, help="root holding the octolgp to use")
    p.add_argument("--repo", type=Path, required=True, help="repository with the input data")
    p.add_argument("--sim", type=Path, help="the paper2d simulation (.npz), for 'sim'")
    p.add_argument("--out", type=Path, required=True, help="result .npz")
    p.add_argument("--intel-scans", type=int, default=120)
    p.add_argument("--gp-scans", type=int, default=None, help="gp on the first N sim scans")
    p.add_argument("--datasets", default=",".join(DATASETS))
    args = p.parse_args(argv)
    octolgp = _import_octolgp(args.tree)
    datasets = [d for d in args.datasets.split(",") if d]
    timings: dict[str, float] = {}
    res: Results = {}
    runners: dict[str, Callable[[], Results]] = {
        "intel": lambda: run_intel(octolgp, args.repo, args.intel_scans),
        "sim": lambda: run_sim(octolgp, args.sim, args.gp_scans, timings),
        "3dtk": lambda: run_3dtk(octolgp, args.repo),
    }
    errors: dict[str, str] = {}
    for name in datasets:
        if name not in runners:
            raise SystemExit(f"driver: unknown data set {name!r} (known: {', '.join(DATASETS)})")
        t0 = time.perf_counter()
        try:
            res.update(runners[name]())
        except Exception:  # one data set failing must not hide the others
            errors[name] = traceback.format_exc()
            print(f"{name} failed:\n{errors[name]}", flush=True)
        timings[name] = time.perf_counter() - t0
        print(f"{name}: {timings[name]:.1f} s", flush=True)
    meta = {
        "octolgp_file": str(Path(octolgp.__file__).resolve()),
        "timings": timings,
        "datasets": datasets,
        "errors": errors,
    }
    res["meta.json"] = np.array(json.dumps(meta))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
