"""Command line: ``octolgp simulate | bench``.

The CLI is the only place that exits. A user error prints one line on stderr and
exits 2 (``--debug`` shows the traceback). Heavy modules are imported lazily so
``--help`` is instant.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from octolgp import __version__
from octolgp.errors import OctolgpError

EXAMPLES = """examples:
  octolgp simulate paper2d --out paper2d.npz --seed 0
  octolgp bench paper2d --out bench_out
"""


def _cmd_simulate(args: argparse.Namespace) -> int:
    from octolgp.io import save_scan_log
    from octolgp.simulate import simulate_paper2d

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


def make_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = argparse.ArgumentParser(
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
    sim.add_argument("--seed", type=int, default=0)
    sim.set_defaults(func=_cmd_simulate)

    bench = sub.add_parser("bench", help="reproduce the paper's Table II, Fig. 2-4")
    bench.add_argument("scene", choices=["paper2d"])
    bench.add_argument("--out", default="bench_out", help="folder for the table and figures")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--repeats", type=int, default=5, help="timing runs per method")
    bench.add_argument("--seeds", type=int, default=5, help="simulated data sets for the AUC")
    bench.set_defaults(func=_cmd_bench)
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
