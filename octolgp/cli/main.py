"""Command line: ``octolgp simulate | run | build | replay | query | export | bench | eval``.

The CLI is the only place that exits. A user error prints one line on stderr and
exits 2 (``--debug`` shows the traceback). Heavy modules are imported lazily so
``--help`` is instant.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

from octolgp import __version__
from octolgp.errors import OctolgpError

EXAMPLES = """examples:
  octolgp simulate paper2d --out paper2d.npz --seed 0
  octolgp run data/intel_lab/intel-corrected.log.gz --out intel.octolgp --rerun-save intel.rrd
  octolgp build data/intel_lab/intel-corrected.log.gz --out intel.octolgp --scheduler local
  octolgp replay intel.rrd --out intel2.octolgp
  octolgp query intel.octolgp --points pts.npy --out prob.npy
  octolgp export intel.octolgp --out intel.bt
  octolgp bench paper2d --out bench_out
  octolgp eval data/intel_lab/intel-corrected.log.gz --seeds 5 --out eval_intel
"""


def _cmd_simulate(args: argparse.Namespace) -> int:
    from octolgp.io import save_scan_log
    from octolgp.sim.scenes import simulate_paper2d

    data = simulate_paper2d(seed=args.seed)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise OctolgpError(f"--out must end in .npz, got {str(out)!r}")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_scan_log(out, data.scans, data.truth_points, data.truth_labels)
    n = sum(len(s) for s in data.scans)
    print(
        f"wrote {out}: {len(data.scans)} scans, {n} beams, {data.truth_points.shape[0]} test points"
    )
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from octolgp.bench.paper2d import format_table, run_paper2d

    out = Path(args.out)
    result = run_paper2d(out, seed=args.seed, repeats=args.repeats, n_seeds=args.seeds)
    table = format_table(result)
    print(table)
    (out / "table2.txt").write_text(table + "\n")
    print(f"\nwrote {out}/table2.txt, fig3_maps.png, fig4_roc.png, fig2_1d.png")
    return 0


def _cmd_build(args: argparse.Namespace) -> int:
    import itertools
    import os

    from octolgp.batch.build import SCHEDULED
    from octolgp.batch.leafmap import build_tiled
    from octolgp.batch.voxelized import build_voxelized
    from octolgp.config import MapConfig, OnlineConfig

    out = Path(args.out)
    if args.method not in SCHEDULED and args.scheduler is not None:
        raise OctolgpError(
            f"--scheduler runs --method {' or '.join(SCHEDULED)} only, got --method {args.method}"
        )
    if out.exists() and not args.overwrite:
        raise OctolgpError(f"--out {str(out)!r} already exists (pass --overwrite to replace it)")
    first, scans = _first_and_rest(args.scans, args.format, args.skip_bad)
    scan_list = list(itertools.islice(scans, args.limit))
    if args.downsample is not None:
        scan_list = [s.downsample(args.downsample) for s in scan_list]
    config = MapConfig(
        dim=first.dim,
        resolution=args.resolution,
        online=OnlineConfig(learn_scans=args.learn_scans),
        memory_budget_mb=args.memory_budget,
    )
    scheduler = args.scheduler
    if not args.quiet:
        where = "this process" if scheduler is None else f"Dask ({scheduler})"
        print(f"building {len(scan_list)} scans in {where} ...", file=sys.stderr, flush=True)
    # build beside the target and rename at the end: a killed build leaves no half map
    partial = out.with_name(out.name + ".partial")
    partial.unlink(missing_ok=True)
    from tqdm import tqdm

    bar = tqdm(total=0, unit="leaf", disable=args.quiet or None, dynamic_ncols=True)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        if args.method == "leaf":
            m = build_tiled(
                scan_list,
                config,
                path=partial,
                scheduler=scheduler,
                workers=args.workers,
                n_jobs=args.jobs,
                progress=progress,
            )
        else:
            m = build_voxelized(
                scan_list,
                config,
                args.method,
                path=partial,
                progress=progress,
                scheduler=scheduler,
                n_jobs=args.jobs,
            )
    finally:
        bar.close()
    stats = m.build_stats
    m.close()
    os.replace(partial, out)
    print(
        f"wrote {out}: {len(scan_list)} scans, {int(stats['items'])} training items, "
        f"{int(stats['leaves'])} leaves, {int(stats['voxels'])} voxels in "
        f"{stats['training'] + stats['assign'] + stats['fit'] + stats['store']:.1f} s "
        f"(fit {stats['fit']:.1f} s)"
    )
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    import itertools
    import json

    from octolgp.bench.evaluation import evaluate_log, plot_roc
    from octolgp.config import MapConfig

    if not (0.0 < args.fraction < 1.0):
        raise OctolgpError(f"--fraction must be in (0, 1), got {args.fraction}")
    if not (args.short >= 0.0 and args.short < float("inf")):
        raise OctolgpError(f"--short must be a finite number >= 0, got {args.short}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    first, scans = _first_and_rest(args.scans, args.format, args.skip_bad)
    scan_list = list(itertools.islice(scans, args.limit))
    config = MapConfig(dim=first.dim, resolution=args.resolution)

    def progress(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    report = evaluate_log(
        scan_list,
        config,
        seeds=args.seeds,
        fraction=args.fraction,
        run=args.run,
        short=args.short,
        leave_one_out=args.leave_one_out,
        methods=methods,
        n_jobs=args.jobs,
        downsample=args.downsample,
        progress=progress,
        fast_online=args.fast_online,
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = Path(args.scans).name
    plot_roc(report, out / "roc.png", title=f"{name}: held-out scans")
    (out / "results.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    table = f"{name}, {len(scan_list)} scans, resolution {args.resolution} m: " + report.table()
    (out / "table.md").write_text(table + "\n")
    print(table)
    print(f"\nwrote {out}/roc.png, {out}/results.json, {out}/table.md")
    return 0


def _first_and_rest(
    path: str, fmt: str | None, skip_bad: bool = False
) -> tuple[Any, Iterator[Any]]:
    """The first scan of a log (to learn its dimension) and an iterator over all of them.

    With ``skip_bad`` the reader skips malformed parts; once the iterator is exhausted a
    line on stderr says how many it skipped.
    """
    import itertools

    from octolgp.io import load_scans

    reader = load_scans(path, format=fmt, skip_bad=skip_bad)
    it = iter(reader)

    def report() -> Iterator[Any]:
        # a generator: runs only once the reader is exhausted
        skipped = getattr(reader, "skipped", 0)
        if skip_bad and skipped:
            print(f"octolgp: skipped {skipped} malformed part(s) of {path}", file=sys.stderr)
        yield from ()

    first = next(it, None)
    if first is None:
        raise OctolgpError(f"SCANS {path!r} holds no scans")
    return first, itertools.chain([first], it, report())


def _recording(args: argparse.Namespace) -> Any:
    """The Rerun recording the options ask for, or ``None``."""
    wants = [args.rerun_save, args.rerun_connect, args.rerun_serve]
    if not any(wants):
        return None
    import rerun as rr

    rec = rr.RecordingStream("octolgp")
    try:
        if args.rerun_save:
            where = f"--rerun-save {args.rerun_save!r}"
            rec.save(args.rerun_save)
        elif args.rerun_connect:
            where = f"--rerun-connect {args.rerun_connect!r}"
            rec.connect_grpc(args.rerun_connect)
        else:
            where = "--rerun-serve"
            url = rec.serve_grpc()
            print(f"serving the recording at {url} (open it with: rerun --connect {url})")
    except (RuntimeError, ValueError, TypeError) as exc:  # how rerun reports a bad path or URL
        raise OctolgpError(f"{where}: {exc}") from None
    return rec


def _map_scans(scans: Iterator[Any], first: Any, args: argparse.Namespace) -> int:
    """Insert scans one by one into a new map file (progress bar in scans/s)."""
    import itertools

    from tqdm import tqdm

    from octolgp.config import MapConfig, OnlineConfig
    from octolgp.mapping.online import OnlineMap

    out = Path(args.out)
    resume = getattr(args, "resume", False) and out.exists()
    if out.exists() and not (args.overwrite or resume):
        raise OctolgpError(
            f"--out {str(out)!r} already exists (pass --resume to continue it, "
            "--overwrite to replace it)"
        )
    if args.limit is not None:
        scans = itertools.islice(scans, args.limit)
    config = MapConfig(
        dim=first.dim,
        resolution=args.resolution,
        online=OnlineConfig(n_jobs=args.jobs, learn_scans=args.learn_scans),
        memory_budget_mb=args.memory_budget,
    )
    rec = _recording(args)
    sink = None
    if rec is not None:
        from octolgp.sinks.rerun import RerunSink

        sink = RerunSink(rec, rays=args.rerun_rays, uncertainty=args.rerun_uncertainty)
    if resume:
        m = OnlineMap.open(out)
        if m.config.dim != config.dim or m.config.resolution != config.resolution:
            m.close()
            raise OctolgpError(
                f"--resume: {str(out)!r} is a {m.config.dim}D map at {m.config.resolution:g} m, "
                f"the scans are {config.dim}D and --resolution is {config.resolution:g} m"
            )
        m.sink = m.sink if sink is None else sink
        done = m.n_scans
        scans = itertools.islice(scans, done, None)  # skip what the map already holds
        print(f"resuming {out} after {done} scans")
    else:
        for suffix in ("", "-wal", "-shm"):
            Path(str(out) + suffix).unlink(missing_ok=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        m = OnlineMap(config, path=out, sink=sink)
    try:
        with m:
            bar = tqdm(scans, unit="scan", disable=args.quiet or None, dynamic_ncols=True)
            repaired = 0
            for scan in bar:  # one iteration per scan
                update = m.insert_scan(scan)
                repaired += update.repaired
                bar.set_postfix(leaves=update.n_leaves, refit=update.refit_leaves, refresh=False)
            last = m.flush()
            repaired += 0 if last is None else last.repaired
            n_leaves, n_scans = len(m.store), m.n_scans
    finally:
        if rec is not None:
            rec.flush()
            rec.disconnect()
    print(f"wrote {out}: {n_scans} scans, {n_leaves} leaves, hyperparameters {m.hyperparameters}")
    if repaired:
        print(
            f"note: {repaired} leaf kernel matrices were not positive definite; repaired by jitter"
        )
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    first, scans = _first_and_rest(args.scans, args.format, args.skip_bad)
    return _map_scans(scans, first, args)


def _cmd_replay(args: argparse.Namespace) -> int:
    import itertools

    from octolgp.io.rrd_read import read_rrd

    reader = read_rrd(
        args.recording,
        points=args.points,
        pose=args.pose,
        timeline=args.timeline,
        max_range=args.max_range,
    )
    it = iter(reader)
    first = next(it, None)
    if first is None:
        raise OctolgpError(f"recording {args.recording!r} holds no scans")
    status = _map_scans(itertools.chain([first], it), first, args)
    for note in getattr(reader, "notes", []):
        print(f"note: {note}")
    return status


def _cmd_query(args: argparse.Namespace) -> int:
    import numpy as np

    from octolgp.mapping.online import OnlineMap

    pts_path = Path(args.points)
    if not pts_path.is_file():
        raise OctolgpError(f"--points {str(pts_path)!r} does not exist")
    try:
        pts = np.load(pts_path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise OctolgpError(f"--points {str(pts_path)!r} is not a .npy array: {exc}") from None
    with OnlineMap.open(args.map) as m:
        prob = m.occupancy(pts, interpolate=not args.nearest)
    np.save(args.out, prob)
    print(f"wrote {args.out}: P(occupied) at {prob.size} points")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    import numpy as np

    from octolgp.export.octomap import write_ply, write_png
    from octolgp.mapping.online import OnlineMap

    out = Path(args.out)
    kinds = (".bt", ".ot", ".ply", ".png")
    if out.suffix not in kinds:
        raise OctolgpError(f"--out must end in one of {', '.join(kinds)}, got {str(out)!r}")
    with OnlineMap.open(args.map) as m:
        if out.suffix in (".bt", ".ot"):
            nodes = m.export_octomap(out, threshold=args.threshold)
            print(f"wrote {out}: {nodes} OctoMap nodes")
            return 0
        centres, prob = m.voxels()
        res = m.config.resolution
    if out.suffix == ".ply":
        keep = prob > args.threshold
        write_ply(out, centres[keep], prob[keep])
        print(f"wrote {out}: {int(keep.sum())} occupied voxel centres with P(occupied)")
        return 0
    if centres.shape[1] == 3:  # a height slice of a 3D map
        z = args.z if args.z is not None else float(np.median(centres[:, 2]))
        layer = np.floor(centres[:, 2] / res) == np.floor(z / res)
        centres, prob = centres[layer, :2], prob[layer]
    write_png(out, centres, prob, res)
    print(f"wrote {out}: {prob.size} voxels")
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _nonnegative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must be a number in (0, 1), got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _scan_log_options(p: argparse.ArgumentParser) -> None:
    """The scan log argument and how to read it, shared by run, build and eval."""
    p.add_argument(
        "scans",
        help="scan log: npz, CARMEN .log/.clf[.gz], 3DTK folder, .rrd, ROS bag, PCD, PLY, "
        "OctoMap scan.dat/.graph",
    )
    p.add_argument("--format", default=None, help="scan log format (default: guessed)")
    p.add_argument(
        "--skip-bad", action="store_true", help="skip malformed lines/messages and count them"
    )


def _mapping_options(p: argparse.ArgumentParser) -> None:
    """Options shared by the subcommands that map scans online."""
    p.add_argument("--out", required=True, help="map file to write (.octolgp, SQLite)")
    p.add_argument("--resolution", type=_positive_float, default=0.1, help="metres")
    p.add_argument("--jobs", type=_positive_int, default=1, help="threads refitting leaves")
    p.add_argument(
        "--learn-scans", type=_positive_int, default=40, help="scans to learn hyperparameters on"
    )
    p.add_argument("--limit", type=_positive_int, default=None, help="stop after N scans")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument(
        "--resume", action="store_true", help="continue an existing --out after its last scan"
    )
    p.add_argument(
        "--memory-budget",
        type=_positive_float,
        default=None,
        metavar="MB",
        help="RAM for leaves; the rest stays in the map file",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    rr = p.add_mutually_exclusive_group()
    rr.add_argument("--rerun-save", metavar="REC.rrd", help="stream the mapping to a recording")
    rr.add_argument("--rerun-connect", metavar="URL", help="stream to a viewer (rerun+http://...)")
    rr.add_argument("--rerun-serve", action="store_true", help="serve the stream over gRPC")
    p.add_argument(
        "--rerun-rays", type=_nonnegative_int, default=0, help="log every k-th beam as a ray"
    )
    p.add_argument("--rerun-uncertainty", action="store_true", help="log the variance layer")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``octolgp <cmd>: error: message`` (no usage block) and exit 2."""
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see --help)\n")


def make_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = _Parser(
        prog="octolgp",
        description="Continuous occupancy maps with overlapping local Gaussian processes.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"octolgp {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="write a simulated data set with ground truth")
    sim.add_argument("scene", choices=["paper2d"], help="the paper's 2D simulation")
    sim.add_argument("--out", required=True, help="output .npz scan log")
    sim.add_argument("--seed", type=_nonnegative_int, default=0)
    sim.set_defaults(func=_cmd_simulate)

    run = sub.add_parser("run", help="map a scan log online, scan by scan")
    _scan_log_options(run)
    _mapping_options(run)
    run.set_defaults(func=_cmd_run)

    replay = sub.add_parser("replay", help="rebuild a map from a Rerun recording")
    replay.add_argument("recording", help="Rerun recording (.rrd)")
    replay.add_argument("--points", default=None, help="points entity (default: found)")
    replay.add_argument("--pose", default=None, help="Transform3D entity (default: found)")
    replay.add_argument("--timeline", default=None, help="timeline (default: found)")
    replay.add_argument(
        "--max-range", type=_positive_float, default=None, help="no-return range, metres"
    )
    _mapping_options(replay)
    replay.set_defaults(func=_cmd_replay)

    query = sub.add_parser("query", help="P(occupied) at query points of a map file")
    query.add_argument("map", help="map file written by run")
    query.add_argument("--points", required=True, help=".npy array of shape (q, d)")
    query.add_argument("--out", required=True, help=".npy file for the probabilities")
    query.add_argument(
        "--nearest",
        action="store_true",
        help="the value of the voxel holding each point (default: interpolated, continuous)",
    )
    query.set_defaults(func=_cmd_query)

    export = sub.add_parser("export", help="export a map file to OctoMap, PLY or PNG")
    export.add_argument("map", help="map file written by run or replay")
    export.add_argument("--out", required=True, help="FILE.bt | FILE.ot | FILE.ply | FILE.png")
    export.add_argument(
        "--threshold", type=_probability, default=0.5, help="occupied above this P, in (0, 1)"
    )
    export.add_argument("--z", type=float, default=None, help="height of a 3D map's PNG slice")
    export.set_defaults(func=_cmd_export)

    bench = sub.add_parser("bench", help="reproduce the paper's Table II, Fig. 2-4")
    bench.add_argument("scene", choices=["paper2d"])
    bench.add_argument("--out", default="bench_out", help="folder for the table and figures")
    bench.add_argument("--seed", type=_nonnegative_int, default=0)
    bench.add_argument("--repeats", type=_positive_int, default=5, help="timing runs per method")
    bench.add_argument(
        "--seeds", type=_positive_int, default=5, help="simulated data sets for the AUC"
    )
    bench.set_defaults(func=_cmd_bench)

    bld = sub.add_parser(
        "build",
        help="batch-build a map file from a whole log, each leaf fitted once",
        description=(
            "Build the map of a whole log in one step: every octree leaf is fitted once, "
            "on --jobs threads here or as tasks on a dask.distributed cluster "
            "(--scheduler local for an embedded LocalCluster, or tcp://HOST:PORT)."
        ),
    )
    _scan_log_options(bld)
    bld.add_argument("--out", required=True, help="map file to write (.octolgp, SQLite)")
    bld.add_argument("--resolution", type=_positive_float, default=0.1, help="metres")
    bld.add_argument(
        "--method",
        choices=["leaf", "lgp", "gp", "mgp", "ogm"],
        default="leaf",
        help="leaf: the online map's overlapping local GPs, each octree leaf fitted once "
        "(default); lgp: the paper's k-means local GPs; gp, mgp, ogm: the baselines "
        "(all but leaf stored as their values at the voxel centres)",
    )
    bld.add_argument("--jobs", type=_positive_int, default=1, help="threads fitting leaves")
    bld.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="'local' (embedded LocalCluster) or a dask scheduler address tcp://HOST:PORT",
    )
    bld.add_argument(
        "--workers", type=_positive_int, default=None, help="LocalCluster worker processes"
    )
    bld.add_argument(
        "--learn-scans", type=_positive_int, default=40, help="scans to learn hyperparameters on"
    )
    bld.add_argument("--downsample", type=_positive_float, default=None, metavar="VOXEL")
    bld.add_argument("--limit", type=_positive_int, default=None, help="use the first N scans")
    bld.add_argument(
        "--memory-budget", type=_positive_float, default=None, metavar="MB", help="RAM for leaves"
    )
    bld.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    bld.add_argument("--quiet", action="store_true", help="no progress messages")
    bld.set_defaults(func=_cmd_build)

    ev = sub.add_parser(
        "eval",
        help="held-out-scan AUC of octolgp online and batch, the grid and OctoMap",
        description=(
            "Hold out 10%% of the scans in contiguous runs, label held-out endpoints "
            "occupied and points along the beams free, map the rest with every method "
            "and report ROC AUC and the unknown fraction (mean ± std over seeds)."
        ),
    )
    _scan_log_options(ev)
    ev.add_argument("--resolution", type=_positive_float, default=0.1, help="metres")
    ev.add_argument("--seeds", type=_positive_int, default=5, help="random splits")
    ev.add_argument("--fraction", type=_positive_float, default=0.1, help="held-out share")
    ev.add_argument("--run", type=_positive_int, default=40, help="longest held-out run")
    ev.add_argument("--short", type=float, default=0.1, help="metres kept free before each hit")
    ev.add_argument("--leave-one-out", action="store_true", help="hold out each scan once instead")
    ev.add_argument(
        "--methods",
        default="online,batch,grid,octomap",
        help="comma-separated subset of online,batch,grid,octomap",
    )
    ev.add_argument("--downsample", type=_positive_float, default=None, metavar="VOXEL")
    ev.add_argument("--limit", type=_positive_int, default=None, help="use the first N scans")
    ev.add_argument("--jobs", type=_positive_int, default=1, help="threads for the GP methods")
    ev.add_argument("--out", default="eval_out", help="folder for roc.png, results.json")
    ev.add_argument(
        "--fast-online",
        action="store_true",
        help="build the online map in one step (the same map, bit for bit; not its timing)",
    )
    ev.add_argument("--quiet", action="store_true", help="no progress messages")
    ev.set_defaults(func=_cmd_eval)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 bad input)."""
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (OctolgpError, OSError) as exc:
        if args.debug:
            raise
        message = " ".join(str(exc).split())
        print(f"octolgp: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
