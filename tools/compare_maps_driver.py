"""Driver of ``tools/compare_maps.py``: build the comparison maps with one copy of octolgp.

It is run in a subprocess once per code tree, with ``PYTHONPATH`` set to that tree,
and uses only the public API that every version of the package shares
(``from octolgp import ...``: ``MapConfig``, ``OnlineConfig``, ``Hyperparameters``,
``OnlineMap``, ``Scan``, ``load_scans``, ``build_map``, ``learn_hyperparameters``, and
the maps' ``voxels``, ``occupancy``, ``latent``, ``flush``, ``correct_scans``), so it runs
unchanged against a baseline commit and against the restructured working tree. Nothing
is looked up with ``getattr`` or ``hasattr`` on the online maps: an attribute one version
lacks fails that data set (its traceback is recorded) rather than being skipped.

It writes one ``.npz`` whose keys are ``"<data set>.<map>.<field>"`` plus ``"meta.json"``
(the octolgp file imported, timings, and the traceback of every unit that failed; the
others still run). A unit is one data set with one leaf engine (``intel/exact``), or
the sim's batch maps (``sim/batch``); its maps are named by the engine
(``lattice_voxels``, ``exact_grid``, ...).

Usage (normally called by ``compare_maps.py``)::

    PYTHONPATH=TREE python -P tools/compare_maps_driver.py --tree TREE --repo REPO
        --sim SIM.npz --dynamic3d DYN.npz --out RESULT.npz [--intel-scans N]
        [--exact-intel-scans N] [--exact-dynamic-scans N] [--correct-scans N]
        [--datasets intel,sim,3dtk,dynamic3d,corrected] [--engines lattice,exact]

    PYTHONPATH=BASELINE python -P tools/compare_maps_driver.py --tree BASELINE
        --repo REPO --make-dynamic3d DYN.npz

``--tree`` is the root that must hold the imported ``octolgp`` (the run fails
otherwise); ``--repo`` is where the input data live (``data/`` and
``tests/data/``), the same for every tree. ``--make-dynamic3d`` writes the simulated
3D lidar scans of the ``dynamic3d`` data set (with the tree's
``octolgp.sim.dynamic.simulate_dynamic_room3d``, all its arguments given) as an npz
scan log and exits; ``compare_maps.py`` does that once, with the baseline, so both
runs map the same scans whatever the candidate's simulator does.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np

DATASETS = ("intel", "sim", "3dtk", "dynamic3d", "corrected")
ENGINES = ("lattice", "exact")
SIM_METHODS = ("lgp", "gp", "mgp", "ogm")
INTEL_LOG = Path("data/intel_lab/intel-corrected.log.gz")
THREEDTK_DIR = Path("tests/data/3dtk")
GRID_SIDE = 501  # the Intel query grid: GRID_SIDE x GRID_SIDE points over the map's extent
GRID_3D = (48, 36, 16)  # the dynamic3d query grid, points per axis over the map's extent

# The simulated scene of ``dynamic3d``: every argument of simulate_dynamic_room3d given,
# so that a change of its defaults changes nothing here (the baseline writes it anyway).
DYNAMIC3D_SCENE = {
    "n_scans": 48,
    "scans_per_lap": 16,
    "n_azimuth": 360,
    "n_elevation": 16,
    "fov_down": -25.0,
    "fov_up": 15.0,
    "max_range": 10.0,
    "cube_moves_at": 16,
    "voxel_filter": 0.2,
}
# Given hyperparameters (tools/bench_dynamic.py's HP_3D and HP_2D: what the default
# learning gives on its scenes), as keyword arguments of Hyperparameters.
HP_DYNAMIC3D = {
    "length_scale": 3.4,
    "signal_variance": 71.0,
    "noise_variance": 0.01,
    "alpha": 4.8,
    "beta": 0.11,
}
HP_CORRECTED = {
    "length_scale": 0.85,
    "signal_variance": 1.8,
    "noise_variance": 0.01,
    "alpha": 4.3,
    "beta": 0.0,
}
# corrected: (scan number from 1 as a fraction of the scans, yaw in degrees, dx, dy), a
# rigid move about the scan's own origin.
CORRECTIONS = ((1 / 3, 0.8, 0.05, -0.03), (2 / 3, -1.5, -0.04, 0.06))

Results = dict[str, np.ndarray]


def _import_octolgp(tree: Path) -> Any:
    """Import octolgp and check that it is the copy under ``tree``."""
    import octolgp

    where = Path(octolgp.__file__).resolve()
    print(f"octolgp imported from {where}", flush=True)
    if not where.is_relative_to(tree.resolve()):
        raise SystemExit(f"driver: octolgp comes from {where}, not from the tree {tree}")
    return octolgp


def _config(octolgp: Any, engine: str, **kwargs: Any) -> Any:
    """``MapConfig(**kwargs)``; the exact engine as ``online=OnlineConfig(engine="exact")``.

    The lattice maps pass no ``online`` section at all: the default engine, as a user
    who never names one gets it.
    """
    if engine == "exact":
        kwargs["online"] = octolgp.OnlineConfig(engine="exact")
    elif engine != "lattice":
        raise SystemExit(f"driver: unknown engine {engine!r}")
    return octolgp.MapConfig(**kwargs)


def _check_engine(m: Any, engine: str) -> None:
    """Fail unless map ``m`` runs ``engine`` (``m.config.online.engine``)."""
    got = m.config.online.engine
    if got != engine:
        raise RuntimeError(f"the map runs engine {got!r}, asked for {engine!r}")


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


def _record_points(res: Results, prefix: str, m: Any, points: np.ndarray) -> None:
    """Occupancy and (interpolated) latent values of ``m`` at ``points``."""
    res[f"{prefix}.points"] = points
    res[f"{prefix}.prob"] = m.occupancy(points)
    mean, var = m.latent(points)
    res[f"{prefix}.mean"] = mean
    res[f"{prefix}.var"] = var


def _extent_grid(centres: np.ndarray, side: tuple[int, ...]) -> np.ndarray:
    """A regular grid of ``side`` points per axis over the box of ``centres``.

    Its points fall anywhere in the voxels, so the interpolating queries are exercised.
    """
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    axes = [np.linspace(a, b, n) for a, b, n in zip(lo, hi, side, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))


def _online(octolgp: Any, scans: list[Any], config: Any, engine: str) -> Any:
    """An OnlineMap fed scan by scan, with no query in between, then flushed.

    ``flush()`` learns on the buffered scans when a data set has fewer than
    ``learn_scans`` scans. The baseline learnt at the first read instead (the defect of
    issue #13); both versions have ``flush``, so the two maps are the same call.
    """
    m = octolgp.OnlineMap(config)
    _check_engine(m, engine)
    for scan in scans:
        m.insert_scan(scan)
    m.flush()
    return m


def _intel_scans(octolgp: Any, repo: Path, n_scans: int) -> list[Any]:
    """The first ``n_scans`` scans of the Intel log."""
    reader = octolgp.load_scans(repo / INTEL_LOG)
    scans = list(islice(reader, n_scans))
    close = getattr(reader, "close", None)  # a generator or a reader object: either is fine
    if close is not None:
        close()
    return scans


def run_intel(octolgp: Any, repo: Path, n_scans: int, engine: str) -> Results:
    """The first ``n_scans`` of the Intel log, online, 2D at 0.1 m, hyperparameters learnt."""
    scans = _intel_scans(octolgp, repo, n_scans)
    print(f"  intel/{engine}: {len(scans)} scans", flush=True)
    m = _online(octolgp, scans, _config(octolgp, engine, dim=2, resolution=0.1), engine)
    res: Results = {}
    _record_online(res, f"intel.{engine}", m)
    grid = _extent_grid(res[f"intel.{engine}_voxels.centres"], (GRID_SIDE, GRID_SIDE))
    _record_points(res, f"intel.{engine}_grid", m, grid)
    return res


def _sim_scans(octolgp: Any, sim: Path) -> tuple[list[Any], np.ndarray]:
    scans = list(octolgp.load_scans(sim))
    with np.load(sim) as f:
        truth = np.asarray(f["truth_points"])
    return scans, truth


def run_sim_online(octolgp: Any, sim: Path, engine: str) -> Results:
    """The paper's 2D simulation, online at 0.1 m (hyperparameters learnt), at the truth points."""
    scans, truth = _sim_scans(octolgp, sim)
    print(f"  sim/{engine}: {len(scans)} scans, {len(truth)} truth points", flush=True)
    m = _online(octolgp, scans, _config(octolgp, engine, dim=2, resolution=0.1), engine)
    res: Results = {}
    _record_online(res, f"sim.{engine}", m)
    _record_points(res, f"sim.{engine}_truth", m, truth)
    return res


def run_sim_batch(
    octolgp: Any, sim: Path, gp_scans: int | None, timings: dict[str, float]
) -> Results:
    """The paper's 2D simulation: batch maps at the truth points and hyperparameter learning."""
    scans, truth = _sim_scans(octolgp, sim)
    res: Results = {"sim.truth.points": truth}

    def config() -> Any:
        return octolgp.MapConfig(dim=2, resolution=0.1)

    for method in SIM_METHODS:
        t0 = time.perf_counter()
        used = scans
        if method == "gp" and gp_scans is not None:
            used = scans[:gp_scans]
            print(f"  sim: gp on the first {len(used)} scans only (--gp-scans)", flush=True)
        b = octolgp.build_map(used, config(), method=method)
        res[f"sim.{method}.prob"] = b.occupancy(truth)
        mean, var = b.latent(truth)  # every batch map has one (ogm: its log-odds view)
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


def run_3dtk(octolgp: Any, repo: Path, engine: str) -> Results:
    """The 3DTK test fixture, online, 3D at 0.2 m, hyperparameters learnt."""
    scans = list(octolgp.load_scans(repo / THREEDTK_DIR))
    print(f"  3dtk/{engine}: {len(scans)} scans", flush=True)
    m = _online(octolgp, scans, _config(octolgp, engine, dim=3, resolution=0.2), engine)
    res: Results = {}
    _record_online(res, f"3dtk.{engine}", m)
    return res


def run_dynamic3d(octolgp: Any, dyn: Path, n_scans: int | None, engine: str) -> Results:
    """The simulated 3D lidar room with a moving cube, online at 0.2 m, hyperparameters given.

    The lattice map forgets (its default ``clear_scans``); the exact one keeps the first
    evidence. ``n_scans`` (``None``: all) limits the scans mapped.
    """
    scans = list(octolgp.load_scans(dyn))
    if n_scans is not None:
        scans = scans[:n_scans]
    print(f"  dynamic3d/{engine}: {len(scans)} scans", flush=True)
    hp = octolgp.Hyperparameters(**HP_DYNAMIC3D)
    config = _config(octolgp, engine, dim=3, resolution=0.2, hyperparameters=hp)
    m = _online(octolgp, scans, config, engine)
    res: Results = {}
    _record_online(res, f"dynamic3d.{engine}", m)
    grid = _extent_grid(res[f"dynamic3d.{engine}_voxels.centres"], GRID_3D)
    _record_points(res, f"dynamic3d.{engine}_grid", m, grid)
    return res


def _rigid_about(origin: np.ndarray, yaw_deg: float, dx: float, dy: float) -> np.ndarray:
    """A 3 x 3 homogeneous 2D transform: turn by ``yaw_deg`` about ``origin``, then move."""
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    rot = np.array([[c, -s], [s, c]])
    t = np.eye(3)
    t[:2, :2] = rot
    t[:2, 2] = origin - rot @ origin + np.array([dx, dy])
    return t


def run_corrected(octolgp: Any, repo: Path, n_scans: int, engine: str) -> Results:
    """Intel's first ``n_scans``, online with a map file, then two scans moved by ``correct_scans``.

    2D at 0.1 m with given hyperparameters; the voxels after the correction and the
    latent values at their centres.
    """
    scans = _intel_scans(octolgp, repo, n_scans)
    corrections = {}
    for fraction, yaw, dx, dy in CORRECTIONS:
        number = max(1, round(fraction * len(scans)))  # scan numbers count from 1
        origin = np.asarray(scans[number - 1].origin, dtype=np.float64)
        corrections[number] = _rigid_about(origin, yaw, dx, dy)
    print(f"  corrected/{engine}: {len(scans)} scans, correcting {sorted(corrections)}", flush=True)
    hp = octolgp.Hyperparameters(**HP_CORRECTED)
    config = _config(octolgp, engine, dim=2, resolution=0.1, hyperparameters=hp)
    res: Results = {}
    with tempfile.TemporaryDirectory(prefix="compare_maps_corrected_") as tmp:
        m = octolgp.OnlineMap(config, path=Path(tmp) / "corrected.octolgp")
        try:
            _check_engine(m, engine)
            for scan in scans:
                m.insert_scan(scan)
            m.flush()
            m.correct_scans(corrections)
            _record_online(res, f"corrected.{engine}", m)
        finally:
            m.close()
    res[f"corrected.{engine}_transforms.matrices"] = np.stack(
        [corrections[k] for k in sorted(corrections)]
    )
    return res


def make_dynamic3d(out: Path) -> None:
    """Write the ``dynamic3d`` scans (``DYNAMIC3D_SCENE``) as an npz scan log at ``out``.

    The arrays of the npz scan log format (``octolgp/io/npz.py``), written with numpy:
    ``origins``, ``points``, ``offsets``, ``max_range`` and ``stamps`` (NaN for none).
    """
    from octolgp.sim.dynamic import simulate_dynamic_room3d

    scene = simulate_dynamic_room3d(**DYNAMIC3D_SCENE)
    scans = scene.scans()
    sizes = [len(s.points) for s in scans]

    def number(v: float | None) -> float:
        return np.nan if v is None else float(v)

    arrays = {
        "origins": np.stack([np.asarray(s.origin, dtype=np.float64) for s in scans]),
        "points": np.concatenate([np.asarray(s.points, dtype=np.float64) for s in scans]),
        "offsets": np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        "max_range": np.array([number(s.max_range) for s in scans]),
        "stamps": np.array([number(s.stamp) for s in scans]),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **arrays)
    stints = "; ".join(
        f"{o.name} at {np.round(box, 2).tolist()} for scans [{a}, {b})"
        for o in scene.objects
        for a, b, box in o.stints
    )
    print(
        f"wrote {out}: {len(scans)} scans, {sum(sizes)} points ({scene.name}; {stints})",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    """Build the maps of the chosen data sets and save them to ``--out``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tree", type=Path, required=True, help="root holding the octolgp to use")
    p.add_argument("--repo", type=Path, required=True, help="repository with the input data")
    p.add_argument("--sim", type=Path, help="the paper2d simulation (.npz), for 'sim'")
    p.add_argument("--dynamic3d", type=Path, help="the 3D lidar scans (.npz), for 'dynamic3d'")
    p.add_argument("--make-dynamic3d", type=Path, help="write the dynamic3d scans here and exit")
    p.add_argument("--out", type=Path, help="result .npz")
    p.add_argument("--intel-scans", type=int, default=120)
    p.add_argument("--exact-intel-scans", type=int, default=30)
    p.add_argument("--exact-dynamic-scans", type=int, default=24)
    p.add_argument("--correct-scans", type=int, default=30)
    p.add_argument("--gp-scans", type=int, default=None, help="gp on the first N sim scans")
    p.add_argument("--datasets", default=",".join(DATASETS))
    p.add_argument("--engines", default=",".join(ENGINES))
    args = p.parse_args(argv)
    octolgp = _import_octolgp(args.tree)
    if args.make_dynamic3d is not None:
        make_dynamic3d(args.make_dynamic3d)
        return 0
    if args.out is None:
        p.error("--out is required")
    datasets = [d for d in args.datasets.split(",") if d]
    engines = [e for e in args.engines.split(",") if e]
    for name, known, given in (("data set", DATASETS, datasets), ("engine", ENGINES, engines)):
        for x in given:
            if x not in known:
                raise SystemExit(f"driver: unknown {name} {x!r} (known: {', '.join(known)})")
    timings: dict[str, float] = {}
    res: Results = {}
    exact_scans = {"lattice": args.intel_scans, "exact": args.exact_intel_scans}
    dynamic_scans = {"lattice": None, "exact": args.exact_dynamic_scans}
    units: dict[str, Callable[[], Results]] = {}
    for name in datasets:
        for engine in engines:
            unit = f"{name}/{engine}"
            if name == "intel":
                units[unit] = lambda e=engine: run_intel(octolgp, args.repo, exact_scans[e], e)
            elif name == "sim":
                units[unit] = lambda e=engine: run_sim_online(octolgp, args.sim, e)
            elif name == "3dtk":
                units[unit] = lambda e=engine: run_3dtk(octolgp, args.repo, e)
            elif name == "dynamic3d":
                units[unit] = lambda e=engine: run_dynamic3d(
                    octolgp, args.dynamic3d, dynamic_scans[e], e
                )
            else:
                units[unit] = lambda e=engine: run_corrected(
                    octolgp, args.repo, args.correct_scans, e
                )
        if name == "sim":
            units["sim/batch"] = lambda: run_sim_batch(octolgp, args.sim, args.gp_scans, timings)
    errors: dict[str, str] = {}
    for unit, run in units.items():
        t0 = time.perf_counter()
        try:
            res.update(run())
        except Exception:  # one unit failing must not hide the others
            errors[unit] = traceback.format_exc()
            print(f"{unit} failed:\n{errors[unit]}", flush=True)
        timings[unit] = time.perf_counter() - t0
        print(f"{unit}: {timings[unit]:.1f} s", flush=True)
    meta = {
        "octolgp_file": str(Path(octolgp.__file__).resolve()),
        "timings": timings,
        "datasets": datasets,
        "engines": engines,
        "units": list(units),
        "errors": errors,
    }
    res["meta.json"] = np.array(json.dumps(meta))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
