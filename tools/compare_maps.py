"""Show that two versions of octolgp build bit-for-bit identical maps, voxel by voxel.

The baseline commit's ``octolgp/`` is exported with ``git archive`` into a temporary
folder; the candidate is the working tree (or, with ``--candidate REV``, another
exported commit). ``tools/compare_maps_driver.py``, which uses only the public API
the versions share, is then run once per tree in a subprocess of the same
interpreter with ``PYTHONPATH`` set to that tree (it checks ``octolgp.__file__``).

Every online map is built with both leaf engines: ``lattice`` (the default; the map
passes no ``online`` section) and ``exact`` (``MapConfig(...,
online=OnlineConfig(engine="exact"))``, every other online setting at its default,
so no forgetting); the rows are named by the engine (``lattice_voxels``,
``exact_voxels``, ...). An online map is fed scan by scan with no query before the
last scan, then flushed; its rows are ``<engine>_voxels`` (the voxels, sorted by
centre, and the latent values at their centres), ``<engine>_hp`` (its
hyperparameters) and, where said, a query at given points (occupancy and
interpolated latent values). Both runs see the same inputs:

``intel``
    The first ``--intel-scans`` (lattice, 120) or ``--exact-intel-scans`` (exact,
    30) scans of ``data/intel_lab/intel-corrected.log.gz``, ``MapConfig(dim=2,
    resolution=0.1)``, hyperparameters learnt by the map; queried on a 501 x 501
    grid over the map's extent (``<engine>_grid``).
``sim``
    The paper's 2D simulation, written once by the baseline's CLI
    (``octolgp simulate paper2d --seed 0``): the online map as for ``intel`` (all
    28 scans), queried at the ``truth_points`` (``<engine>_truth``); and, once,
    ``build_map(..., method=m)`` for lgp, gp, mgp and ogm evaluated at the
    ``truth_points`` and ``learn_hyperparameters`` on the first 40 scans
    (``sim/batch``).
``3dtk``
    The 3DTK fixture ``tests/data/3dtk`` (3 scans), ``MapConfig(dim=3,
    resolution=0.2)``, hyperparameters learnt.
``dynamic3d``
    A simulated 16 x 360 lidar in an 8 x 6 x 3 m room whose 1 m cube moves from A
    to B at scan 16 (``octolgp.sim.dynamic.simulate_dynamic_room3d``, 48 scans,
    voxel-filtered at 0.2 m). The scans are generated once, by the driver with the
    baseline tree, into an npz scan log that both runs read with ``load_scans``, so
    a change of the simulator cannot change the inputs. ``MapConfig(dim=3,
    resolution=0.2)`` with given hyperparameters; the lattice map (forgetting on,
    its default ``clear_scans``) maps all 48 scans, the exact one the first
    ``--exact-dynamic-scans`` (24: eight after the move). Queried on a 48 x 36 x 16
    grid over the map's extent (``<engine>_grid``).
``corrected``
    The first ``--correct-scans`` (30) Intel scans into ``OnlineMap(MapConfig(dim=2,
    resolution=0.1), path=<temporary map file>)`` with given hyperparameters, then
    ``correct_scans`` moving the scans a third and two thirds of the way (10 and 20
    of 30) by small rigid transforms about their origins (0.8° and -1.5°, a few centimetres); the voxels after the
    correction, and the transforms (``<engine>_transforms``).

Voxels are sorted by centre (lexicographic) before the comparison. A row is
identical when every array of it has the same shape, dtype and bytes in both runs
(so the voxel centre sets are the same and ``np.array_equal`` holds). The exit
status is 0 when every row is identical, 1 when one differs and 2 when a run (or
one unit of a run: a data set with one engine) fails; the units that ran are still
compared. Nothing of the API is probed for: an attribute one version lacks fails
that unit in that run, with its traceback.

Usage, from anywhere (the repository is this file's parent's parent)::

    .venv/bin/python tools/compare_maps.py [--baseline REV] [--candidate REV]
        [--datasets intel,sim,3dtk,dynamic3d,corrected] [--engines lattice,exact]
        [--intel-scans N] [--exact-intel-scans N] [--exact-dynamic-scans N]
        [--correct-scans N] [--out DIR]

``--out`` keeps the two result files, the generated inputs and the runs' logs (by
default they go to a temporary folder that is removed). The two runs go in parallel
(``--jobs 2``); on the 2-core development machine the default run takes about
2.5 minutes (``--baseline 86e8419 --candidate 86e8419``: 157 s, 34 rows).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DRIVER = Path(__file__).resolve().parent / "compare_maps_driver.py"
DEFAULT_BASELINE = "86e8419"
DATASETS = ("intel", "sim", "3dtk", "dynamic3d", "corrected")
ENGINES = ("lattice", "exact")
DELTA_FIELDS = ("prob", "mean", "var")  # the fields with a max |Δ| column


@dataclass
class Side:
    """One code tree to run the driver against."""

    label: str
    tree: Path
    description: str


@dataclass
class Row:
    """The comparison of one (data set, map) group of arrays."""

    dataset: str
    name: str
    n: str
    deltas: dict[str, str]
    identical: bool
    note: str


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True
    ).stdout.strip()


def export_tree(rev: str, dest: Path) -> str:
    """Export ``octolgp/`` of commit ``rev`` into ``dest``; return the full hash."""
    full = _git("rev-parse", "--verify", f"{rev}^{{commit}}")
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.Popen(
        ["git", "-C", str(REPO), "archive", full, "octolgp"], stdout=subprocess.PIPE
    )
    subprocess.run(["tar", "-x", "-C", str(dest)], stdin=archive.stdout, check=True)
    if archive.stdout is not None:
        archive.stdout.close()
    if archive.wait() != 0:
        raise SystemExit(f"git archive {full} octolgp failed")
    return full


def _env(tree: Path) -> dict[str, str]:
    """The environment of a run: ``PYTHONPATH`` is the tree alone, no bytecode written."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def make_simulation(tree: Path, out: Path) -> None:
    """Write the paper2d simulation with the CLI of the octolgp under ``tree``."""
    code = (
        "import sys; from pathlib import Path; import octolgp, octolgp.cli; "
        f"where = Path(octolgp.__file__).resolve(); print('simulate with', where); "
        f"assert where.is_relative_to(Path({str(tree.resolve())!r})), where; "
        f"sys.exit(octolgp.cli.main(['simulate', 'paper2d', '--out', {str(out)!r}, "
        "'--seed', '0']))"
    )
    _run_in(tree, [sys.executable, "-P", "-c", code], "simulate paper2d")


def make_dynamic3d(tree: Path, out: Path) -> None:
    """Write the dynamic3d scans with the driver run against the octolgp under ``tree``."""
    cmd = [sys.executable, "-P", str(DRIVER), "--tree", str(tree), "--repo", str(REPO)]
    _run_in(tree, [*cmd, "--make-dynamic3d", str(out)], "writing the dynamic3d scans")


def _run_in(tree: Path, cmd: list[str], what: str) -> None:
    """Run ``cmd`` against the octolgp under ``tree``, echo its output, stop if it fails."""
    done = subprocess.run(cmd, cwd=tree, env=_env(tree), capture_output=True, text=True)
    print("  " + (done.stdout + done.stderr).strip().replace("\n", "\n  "))
    if done.returncode != 0:
        raise SystemExit(f"{what} failed (exit {done.returncode})")


def start_driver(
    side: Side, args: argparse.Namespace, inputs: dict[str, Path], out: Path
) -> subprocess.Popen:
    """Start the driver against one tree; its output goes to ``<out>/<label>.log``."""
    cmd = [
        sys.executable,
        "-P",
        str(DRIVER),
        "--tree",
        str(side.tree),
        "--repo",
        str(REPO),
        "--sim",
        str(inputs["sim"]),
        "--dynamic3d",
        str(inputs["dynamic3d"]),
        "--out",
        str(out / f"{side.label}.npz"),
        "--intel-scans",
        str(args.intel_scans),
        "--exact-intel-scans",
        str(args.exact_intel_scans),
        "--exact-dynamic-scans",
        str(args.exact_dynamic_scans),
        "--correct-scans",
        str(args.correct_scans),
        "--datasets",
        args.datasets,
        "--engines",
        args.engines,
    ]
    if args.gp_scans is not None:
        cmd += ["--gp-scans", str(args.gp_scans)]
    log = (out / f"{side.label}.log").open("w")
    return subprocess.Popen(
        cmd, cwd=side.tree, env=_env(side.tree), stdout=log, stderr=subprocess.STDOUT
    )


def run_drivers(
    sides: list[Side], args: argparse.Namespace, inputs: dict[str, Path], out: Path
) -> bool:
    """Run the driver for every side, ``args.jobs`` at a time; True if all succeeded."""
    ok = True
    pending = list(sides)
    running: list[tuple[Side, subprocess.Popen, float]] = []
    while pending or running:
        while pending and len(running) < args.jobs:
            side = pending.pop(0)
            running.append((side, start_driver(side, args, inputs, out), time.perf_counter()))
        side, proc, t0 = running.pop(0)
        rc = proc.wait()
        log = (out / f"{side.label}.log").read_text()
        print(f"  {side.label}: exit {rc} after {time.perf_counter() - t0:.1f} s")
        if rc != 0:
            ok = False
            tail = "\n    ".join(log.strip().splitlines()[-25:])
            print(f"  {side.label} failed; the end of its log:\n    {tail}")
    return ok


def _max_abs_delta(a: np.ndarray, b: np.ndarray) -> str:
    """Largest |a - b| (NaN in one array only counts as inf), or why there is none."""
    if a.shape != b.shape:
        return f"shape {a.shape}/{b.shape}"
    if a.size == 0:
        return "0"
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    both_nan = np.isnan(a64) & np.isnan(b64)
    d = np.where(both_nan, 0.0, np.abs(a64 - b64))
    d = np.where(np.isnan(d), np.inf, d)
    worst = float(d.max())
    return "0" if worst == 0.0 else f"{worst:.3g}"


def _hp_text(values: np.ndarray) -> str:
    """Hyperparameter values as recorded by the driver (empty: the map had none)."""
    return "None" if values.size == 0 else "[" + ", ".join(f"{v:.6g}" for v in values) + "]"


def _bit_identical(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def compare(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> list[Row]:
    """One row per (data set, map) group of keys ``"<data set>.<map>.<field>"``."""
    groups: dict[tuple[str, str], list[str]] = {}
    for key in sorted(set(a) | set(b)):
        if not key.startswith("meta."):
            dataset, name, field = key.split(".", 2)
            groups.setdefault((dataset, name), []).append(field)
    rows = []
    for (dataset, name), fields in groups.items():
        notes, identical = [], True
        deltas: dict[str, str] = {}
        for field in fields:
            key = f"{dataset}.{name}.{field}"
            if key not in a or key not in b:
                identical = False
                notes.append(f"{field} only in {'baseline' if key in a else 'candidate'}")
                continue
            same = _bit_identical(a[key], b[key])
            identical &= same
            if field in DELTA_FIELDS:
                deltas[field] = _max_abs_delta(a[key], b[key])
            elif not same and field == "hyperparameters":
                notes.append(f"hyperparameters {_hp_text(a[key])} vs {_hp_text(b[key])}")
            elif not same:
                notes.append(f"{field} differs")
        first = next(
            (
                f
                for f in ("centres", "points", "prob", "hyperparameters", "matrices")
                if f in fields
            ),
            "",
        )
        sizes = [
            len(d[f"{dataset}.{name}.{first}"])
            for d in (a, b)
            if first and f"{dataset}.{name}.{first}" in d
        ]
        n = "/".join(str(size) for size in sizes) if len(set(sizes)) > 1 else "-"
        if len(set(sizes)) == 1:
            n = str(sizes[0])
        rows.append(Row(dataset, name, n, deltas, identical, "; ".join(notes)))
    return rows


def print_table(rows: list[Row]) -> None:
    """The comparison table, one line per row."""
    head = ("data set", "map", "n", "max |ΔP|", "max |Δmean|", "max |Δvar|", "identical")
    lines = [
        (
            r.dataset,
            r.name,
            r.n,
            *(r.deltas.get(f, "-") for f in DELTA_FIELDS),
            "yes" if r.identical else "NO",
        )
        for r in rows
    ]
    widths = [max(len(x) for x in col) for col in zip(head, *lines, strict=True)]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    print(fmt.format(*head).rstrip())
    print("  ".join("-" * w for w in widths))
    for line, row in zip(lines, rows, strict=True):
        print((fmt.format(*line) + (f"  ({row.note})" if row.note else "")).rstrip())


def _load(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def main(argv: list[str] | None = None) -> int:
    """Export, run both sides, compare; see the module docstring."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--baseline", default=DEFAULT_BASELINE, help="baseline commit (git rev)")
    p.add_argument(
        "--candidate", default=None, help="candidate commit; the working tree when omitted"
    )
    p.add_argument("--intel-scans", type=int, default=120, help="Intel scans, lattice (120)")
    p.add_argument(
        "--exact-intel-scans", type=int, default=30, help="Intel scans, exact engine (30)"
    )
    p.add_argument(
        "--exact-dynamic-scans", type=int, default=24, help="dynamic3d scans, exact engine (24)"
    )
    p.add_argument("--correct-scans", type=int, default=30, help="Intel scans of 'corrected' (30)")
    p.add_argument(
        "--datasets",
        default=",".join(DATASETS),
        help=f"comma-separated subset of {','.join(DATASETS)}",
    )
    p.add_argument(
        "--engines",
        default=",".join(ENGINES),
        help="comma-separated leaf engines of the online maps: lattice,exact",
    )
    p.add_argument("--gp-scans", type=int, default=None, help="sim gp on the first N scans only")
    p.add_argument("--jobs", type=int, choices=(1, 2), default=2, help="driver runs at once")
    p.add_argument("--out", type=Path, default=None, help="keep results and logs in this folder")
    args = p.parse_args(argv)
    unknown = set(args.datasets.split(",")) - set(DATASETS)
    if unknown:
        p.error(f"unknown data sets: {', '.join(sorted(unknown))}")
    unknown = set(args.engines.split(",")) - set(ENGINES)
    if unknown:
        p.error(f"unknown engines: {', '.join(sorted(unknown))}")
    for name in ("intel_scans", "exact_intel_scans", "exact_dynamic_scans", "correct_scans"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")

    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="compare_maps_") as tmp_name:
        tmp = Path(tmp_name)
        out = args.out.resolve() if args.out is not None else tmp / "out"
        out.mkdir(parents=True, exist_ok=True)
        base_hash = export_tree(args.baseline, tmp / "baseline")
        sides = [Side("baseline", tmp / "baseline", f"{args.baseline} ({base_hash[:12]})")]
        if args.candidate is None:
            sides.append(Side("candidate", REPO, f"working tree {REPO}"))
        else:
            cand_hash = export_tree(args.candidate, tmp / "candidate")
            sides.append(
                Side("candidate", tmp / "candidate", f"{args.candidate} ({cand_hash[:12]})")
            )
        for side in sides:
            print(f"{side.label}: {side.description}, PYTHONPATH={side.tree}")

        inputs = {"sim": out / "paper2d_seed0.npz", "dynamic3d": out / "dynamic3d.npz"}
        if "sim" in args.datasets.split(","):
            print("simulating paper2d with the baseline CLI")
            make_simulation(sides[0].tree, inputs["sim"])
        if "dynamic3d" in args.datasets.split(","):
            print("simulating the dynamic3d lidar scans with the baseline's simulator")
            make_dynamic3d(sides[0].tree, inputs["dynamic3d"])
        print(f"running the driver ({args.jobs} at a time); logs in {out}")
        if not run_drivers(sides, args, inputs, out):
            print(
                "a run failed: nothing compared (if the working tree is mid-edit, try --candidate REV)"
            )
            return 2
        results = [_load(out / f"{side.label}.npz") for side in sides]

    failed: list[Row] = []
    for side, res in zip(sides, results, strict=True):
        meta = json.loads(str(res["meta.json"]))
        times = ", ".join(f"{k} {v:.1f} s" for k, v in meta["timings"].items())
        print(f"{side.label}: octolgp from {meta['octolgp_file']}\n  timings: {times}")
        for unit, trace in meta["errors"].items():
            last = trace.strip().splitlines()[-1]
            print(
                f"  {unit} FAILED in the {side.label} run:\n    "
                + trace.strip().replace("\n", "\n    ")
            )
            failed.append(Row(unit, "(run failed)", "-", {}, False, f"{side.label}: {last}"))
    rows = compare(*results) + failed
    print()
    print(f"baseline {sides[0].description} vs candidate {sides[1].description}")
    print_table(rows)
    n_diff = sum(not r.identical for r in rows)
    print(
        f"\n{len(rows) - n_diff} of {len(rows)} identical bit for bit; "
        f"total {time.perf_counter() - t_start:.0f} s"
    )
    if failed:
        print(f"{len(failed)} data set run(s) failed: see above")
        return 2
    return 1 if n_diff else 0


if __name__ == "__main__":
    sys.exit(main())
