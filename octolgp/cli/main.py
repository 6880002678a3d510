"""Command line: ``octolgp run | build | replay | query | export | eval | dump-config | ...``.

The CLI is the only place that exits. A user error prints one line on stderr and
exits 2 (``--debug`` shows the traceback). Heavy modules are imported lazily so
``--help`` is instant.

This module holds the argument parser, its shared option types and groups, and
:func:`main`; the commands are in :mod:`octolgp.cli.build` (``simulate``, ``build``,
``eval``, ``bench``), :mod:`octolgp.cli.online` (``run``, ``replay``) and
:mod:`octolgp.cli.maps` (``query``, ``export``, ``correct``); :mod:`octolgp.cli.configs`
resolves the map configuration (``--config``, ``dump-config``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import NoReturn

from octolgp import __version__
from octolgp.cli.build import cmd_bench, cmd_build, cmd_eval, cmd_simulate
from octolgp.cli.configs import add_config_option, add_dump_config
from octolgp.cli.maps import cmd_correct, cmd_export, cmd_info, cmd_query
from octolgp.cli.online import cmd_replay, cmd_run
from octolgp.errors import OctolgpError

__all__ = ["EXAMPLES", "main", "make_parser"]

EXAMPLES = """examples:
  octolgp simulate paper2d --out paper2d.npz --seed 0
  octolgp run data/intel_lab/intel-corrected.log.gz --out intel.octolgp --rerun-save intel.rrd
  octolgp build data/intel_lab/intel-corrected.log.gz --out intel.octolgp --scheduler local
  octolgp replay intel.rrd --out intel2.octolgp
  octolgp query intel.octolgp --points pts.npy --out prob.npy
  octolgp query intel.octolgp --raycast rays.npy --max-range 10 --out hits.csv
  octolgp export intel.octolgp --out intel.bt
  octolgp correct intel.octolgp --poses corrections.txt
  octolgp correct intel.octolgp --absolute optimised_poses.txt
  octolgp bench paper2d --out bench_out
  octolgp eval data/intel_lab/intel-corrected.log.gz --seeds 5 --out eval_intel
  octolgp dump-config --resolution 0.05 > intel.toml
  octolgp run data/intel_lab/intel-corrected.log.gz --config intel.toml --out intel.octolgp
"""

RERUN_COLORS = ("auto", "probability")
"""``--rerun-colors`` choices: :data:`octolgp.sinks.rerun.COLORS` (not imported: rerun is heavy)."""


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
        help="scan log: npz, CARMEN .log/.clf[.gz], 3DTK folder, KITTI sequences/NN, .rrd, "
        "ROS bag, PCD, PLY, OctoMap scan.dat/.graph",
    )
    p.add_argument("--format", default=None, help="scan log format (default: guessed)")
    p.add_argument(
        "--skip-bad", action="store_true", help="skip malformed lines/messages and count them"
    )


def _mapping_options(p: argparse.ArgumentParser) -> None:
    """Options shared by the subcommands that map scans online."""
    p.add_argument("--out", required=True, help="map file to write (.octolgp, SQLite)")
    add_config_option(p)
    p.add_argument("--resolution", type=_positive_float, default=None, help="metres (default 0.1)")
    p.add_argument(
        "--jobs",
        type=_positive_int,
        default=None,
        help="threads refitting leaves (default: the cores available, at most 8)",
    )
    p.add_argument(
        "--learn-scans",
        type=_positive_int,
        default=None,
        help="scans to learn hyperparameters on (default 40 in 2D, 5 in 3D)",
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
    rr.add_argument(
        "--rerun-serve", action="store_true", help="serve the stream over gRPC until Ctrl-C"
    )
    rr.add_argument(
        "--rerun-web",
        action="store_true",
        help="serve the stream and rerun's web viewer (open the printed URL) until Ctrl-C",
    )
    p.add_argument(
        "--rerun-port", type=_positive_int, default=None, metavar="PORT", help="gRPC port (9876)"
    )
    p.add_argument(
        "--rerun-web-port",
        type=_positive_int,
        default=None,
        metavar="PORT",
        help="web viewer port (9090)",
    )
    p.add_argument(
        "--rerun-rays", type=_nonnegative_int, default=0, help="log every k-th beam as a ray"
    )
    p.add_argument("--rerun-uncertainty", action="store_true", help="log the variance layer")
    p.add_argument(
        "--rerun-colors",
        choices=RERUN_COLORS,
        default="auto",
        help="map colours: auto (2D grey occupancy, 3D height) or probability (P(occupied): "
        "blue free, grey unknown, red occupied); a legend view shows which",
    )
    p.add_argument(
        "--rerun-free-voxels",
        action="store_true",
        help="3D: also draw free voxels (P < 0.25; one in 8, at most 4,096 a 32-voxel region)",
    )


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
    parser.add_argument(
        "--log-level",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        default="WARNING",
        help="messages of the octolgp logger shown on stderr (default WARNING)",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="write a simulated data set with ground truth")
    sim.add_argument("scene", choices=["paper2d"], help="the paper's 2D simulation")
    sim.add_argument("--out", required=True, help="output .npz scan log")
    sim.add_argument("--seed", type=_nonnegative_int, default=0)
    sim.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    sim.set_defaults(func=cmd_simulate)

    run = sub.add_parser("run", help="map a scan log online, scan by scan")
    _scan_log_options(run)
    _mapping_options(run)
    run.add_argument(
        "--downsample",
        type=_positive_float,
        default=None,
        metavar="VOXEL",
        help="keep one beam per voxel of this edge, metres (Scan.downsample; for 3D lidar)",
    )
    run.add_argument("--scan-topic", default=None, help="ROS bag: the scans' topic")
    run.add_argument("--pose-topic", default=None, help="ROS bag: a pose topic instead of /tf")
    run.add_argument(
        "--frame", default=None, help="ROS bag: the fixed frame (default: map, else odom)"
    )
    run.add_argument(
        "--kitti-frame",
        choices=["velodyne", "cam0"],
        default="velodyne",
        help="a KITTI sequence's world frame: the Velodyne's at frame 0 (default, z up) or "
        "the poses' camera frame (y down)",
    )
    run.add_argument(
        "--max-range",
        type=_positive_float,
        default=None,
        metavar="M",
        help="no-return range, metres: beams at least this long are no-returns (below the "
        "log's own, where it has one)",
    )
    run.set_defaults(func=cmd_run)

    replay = sub.add_parser("replay", help="rebuild a map from a Rerun recording")
    replay.add_argument("recording", help="Rerun recording (.rrd)")
    replay.add_argument("--points", default=None, help="points entity (default: found)")
    replay.add_argument("--pose", default=None, help="Transform3D entity (default: found)")
    replay.add_argument("--timeline", default=None, help="timeline (default: found)")
    replay.add_argument(
        "--max-range", type=_positive_float, default=None, help="no-return range, metres"
    )
    _mapping_options(replay)
    replay.set_defaults(func=cmd_replay)

    info = sub.add_parser("info", help="what a map file holds (read only)")
    info.add_argument("map", help="map file written by run, build or replay")
    info.add_argument("--json", action="store_true", help="one JSON object instead of lines")
    info.set_defaults(func=cmd_info)

    query = sub.add_parser(
        "query",
        help="P(occupied) at points, ray casts or distances to obstacles on a map file",
        description="One of --points (P(occupied)), --raycast (distance along each ray to "
        "where P(occupied) first reaches --threshold) or --distance (distance to the nearest "
        "occupied voxel); the answer goes to --out as .npy or .csv, one value per row.",
    )
    query.add_argument("map", help="map file written by run")
    what = query.add_mutually_exclusive_group(required=True)
    what.add_argument("--points", help=".npy array of shape (q, d): P(occupied) there")
    what.add_argument(
        "--raycast",
        metavar="RAYS",
        help=".npy array of shape (n, 2d): origins then directions; needs --max-range",
    )
    what.add_argument(
        "--distance",
        metavar="POINTS",
        help=".npy array of shape (q, d): metres to the nearest occupied voxel",
    )
    query.add_argument("--out", required=True, help=".npy or .csv file for the answers")
    query.add_argument(
        "--nearest",
        action="store_true",
        help="--points: the value of the voxel holding each point (default: interpolated)",
    )
    query.add_argument(
        "--max-range", type=float, help="--raycast: metres along each ray (required there)"
    )
    query.add_argument(
        "--threshold",
        type=_probability,
        help="--raycast, --distance: P(occupied) that counts as an obstacle (default 0.5)",
    )
    query.add_argument(
        "--unknown",
        choices=("stop", "free", "occupied"),
        help="--raycast: a ray entering unknown space ends with NaN (stop, default), "
        "passes (free) or hits there (occupied)",
    )
    query.add_argument(
        "--max-distance",
        type=float,
        help="--distance: farther answers are inf, and only voxels this near the points are read",
    )
    query.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    query.set_defaults(func=cmd_query)

    export = sub.add_parser(
        "export",
        help="export a map file to OctoMap, PLY, PCD, PNG, a nav2 map (PGM + YAML) or a mesh (OBJ)",
    )
    export.add_argument("map", help="map file written by run or replay")
    export.add_argument(
        "--out",
        required=True,
        help="FILE.bt | FILE.ot | FILE.ply | FILE.pcd | FILE.png | FILE.pgm (nav2: with FILE.yaml)"
        " | FILE.obj (the P = --threshold level set as a mesh)",
    )
    export.add_argument(
        "--mesh",
        action="store_true",
        help="FILE.ply: the level set as a mesh (3D triangles, 2D segments), not voxel centres",
    )
    export.add_argument(
        "--threshold", type=_probability, default=0.5, help="occupied above this P, in (0, 1)"
    )
    zs = export.add_mutually_exclusive_group()
    zs.add_argument("--z", type=float, default=None, help="height of a 3D map's PNG/PGM slice")
    zs.add_argument(
        "--z-range",
        type=float,
        nargs=2,
        default=None,
        metavar=("ZMIN", "ZMAX"),
        help="3D map to PGM: 2.5D projection of the voxels with centres in [ZMIN, ZMAX]",
    )
    export.add_argument(
        "--occupied-thresh", type=_probability, default=0.65, help="PGM: occupied above this P"
    )
    export.add_argument(
        "--free-thresh", type=_probability, default=0.25, help="PGM: free below this P"
    )
    export.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    export.set_defaults(func=cmd_export)

    correct = sub.add_parser(
        "correct",
        help="move scans of a map file by corrected poses (a loop closure, a pose graph)",
        description="Move journaled scans of a map file and rebuild the leaves they reach, in one\n"
        "transaction. Only scans still in the journal (online.journal_scans) can move.\n\n"
        "--poses FILE     per scan a correction: a rigid transform that moves its\n"
        "                 world-frame origin and points.\n"
        "--absolute FILE  per scan the sensor's new pose in the world frame, as a pose\n"
        "                 graph optimiser writes it: scan i moves by T_new * T_old^-1,\n"
        "                 T_old the pose it was inserted with (kept in the journal).\n\n"
        "Either file has one line per scan: its number (from 1, as run counts scans),\n"
        "then one of\n"
        "  x y yaw                     2D pose (metres, radians)\n"
        "  x y z qx qy qz qw           3D pose (TUM's order, scan number for the time)\n"
        "  r11 r12 tx r21 r22 ty       2D matrix, top 2 rows (or all 9 entries)\n"
        "  r11 r12 r13 tx ... r33 tz   3D matrix, top 3 rows as a KITTI poses line\n"
        "                              (or all 16 entries)\n"
        "'#' starts a comment; numbers are separated by spaces or commas.",
        epilog="examples:\n"
        "  octolgp correct intel.octolgp --poses corrections.txt\n"
        "  # 2D pose graph output: '12 3.05 -1.20 0.013' (scan, x, y, yaw)\n"
        "  octolgp correct intel.octolgp --absolute optimised.txt\n"
        "  # 3D: '12 1.0 2.0 0.5 0 0 0.7071068 0.7071068' (scan, x y z, qx qy qz qw)\n"
        "  octolgp correct street.octolgp --absolute optimised_tum.txt",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    correct.add_argument("map", help="map file written by run (it holds the scans' journal)")
    which = correct.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--poses", metavar="FILE", help="corrections file: rigid transforms that move scans"
    )
    which.add_argument(
        "--absolute",
        metavar="FILE",
        help="absolute sensor poses (a pose graph's optimised poses) the scans move to",
    )
    correct.set_defaults(func=cmd_correct)

    bench = sub.add_parser("bench", help="reproduce the paper's Table II, Fig. 2-4")
    bench.add_argument("scene", choices=["paper2d"])
    bench.add_argument("--out", default="bench_out", help="folder for the table and figures")
    bench.add_argument("--seed", type=_nonnegative_int, default=0)
    bench.add_argument("--repeats", type=_positive_int, default=5, help="timing runs per method")
    bench.add_argument(
        "--seeds", type=_positive_int, default=5, help="simulated data sets for the AUC"
    )
    bench.set_defaults(func=cmd_bench)

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
    add_config_option(bld)
    bld.add_argument(
        "--resolution", type=_positive_float, default=None, help="metres (default 0.1)"
    )
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
        "--learn-scans",
        type=_positive_int,
        default=None,
        help="scans to learn hyperparameters on (default 40 in 2D, 5 in 3D)",
    )
    bld.add_argument("--downsample", type=_positive_float, default=None, metavar="VOXEL")
    bld.add_argument("--limit", type=_positive_int, default=None, help="use the first N scans")
    bld.add_argument(
        "--memory-budget", type=_positive_float, default=None, metavar="MB", help="RAM for leaves"
    )
    bld.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    bld.add_argument("--quiet", action="store_true", help="no progress messages")
    bld.set_defaults(func=cmd_build)

    ev = sub.add_parser(
        "eval",
        help="held-out-scan AUC of octolgp online and batch, the grid and OctoMap",
        description=(
            "Hold out 10% of the scans in contiguous runs, label held-out endpoints "
            "occupied and points along the beams free, map the rest with every method "
            "and report ROC AUC (mean ± std and the worst split), the unknown fraction, "
            "the share of held-out walls no training scan hit, and the learnt "
            "hyperparameters."
        ),
    )
    _scan_log_options(ev)
    add_config_option(ev)
    ev.add_argument("--resolution", type=_positive_float, default=None, help="metres (default 0.1)")
    ev.add_argument("--seeds", type=_positive_int, default=5, help="random splits")
    ev.add_argument("--fraction", type=_positive_float, default=0.1, help="held-out share")
    ev.add_argument("--run", type=_positive_int, default=40, help="longest held-out run")
    ev.add_argument("--short", type=float, default=0.1, help="metres kept free before each hit")
    ev.add_argument("--leave-one-out", action="store_true", help="hold out each scan once instead")
    ev.add_argument(
        "--protocol",
        choices=["endpoint", "hilbert"],
        default="endpoint",
        help="test points: endpoint (each hit, one free point per beam) or hilbert (each "
        "return's hit and max(1, int(d/2)) free points along it, Hilbert maps' protocol)",
    )
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
    ev.set_defaults(func=cmd_eval)

    add_dump_config(sub, _positive_int, _positive_float)
    return parser


def _is_database_error(exc: BaseException) -> bool:
    """Whether ``exc`` is an :class:`sqlite3.Error`.

    Told by its class, without importing the module: the map file's database belongs to
    :mod:`octolgp.persist`.
    """
    return any(c.__module__ == "sqlite3" for c in type(exc).__mro__[:-2])


def _message(exc: Exception, args: argparse.Namespace) -> str:
    """The one-line message of an error that ends a command.

    An :class:`OSError` names its file where it knows it; a database error (a fault the
    map file did not turn into an ``OctolgpError``) and an ``OSError`` without a file
    name are told with the command's map file (``MAP``, else ``--out``).
    """
    text = str(exc) or type(exc).__name__
    known = isinstance(exc, OctolgpError) or getattr(exc, "filename", None) is not None
    if not known:
        path = getattr(args, "map", None) or getattr(args, "out", None)
        kind = "database error" if _is_database_error(exc) else "I/O error"
        text = f"{kind} on {path!r}: {text}" if path else f"{kind}: {text}"
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 bad input or an I/O fault).

    An :class:`~octolgp.errors.OctolgpError`, an :class:`OSError` (a full disk, a denied
    permission) or an :class:`sqlite3.Error` ends the command with one line on stderr and
    exit status 2 (``--debug`` shows the traceback); any other exception is a bug and shows
    its traceback.
    """
    parser = make_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(format="octolgp: %(levelname)s: %(message)s")
    logging.getLogger("octolgp").setLevel(args.log_level)
    try:
        return int(args.func(args))
    except Exception as exc:
        reported = isinstance(exc, OctolgpError | OSError) or _is_database_error(exc)
        if args.debug or not reported:
            raise
        print(f"octolgp: error: {_message(exc, args)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
