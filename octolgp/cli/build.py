"""The batch commands: ``simulate``, ``build``, ``eval`` and ``bench``.

Each command takes the parsed arguments and returns the exit status; heavy modules are
imported inside the commands so that ``octolgp --help`` stays instant.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from octolgp.cli.configs import check_outputs
from octolgp.cli.scans import check_scans, first_and_rest
from octolgp.errors import OctolgpError

__all__ = ["cmd_bench", "cmd_build", "cmd_eval", "cmd_simulate"]


def cmd_simulate(args: argparse.Namespace) -> int:
    """``octolgp simulate paper2d``: the paper's 2D simulation, with ground truth, as an npz."""
    from octolgp.export.common import replacing
    from octolgp.io import save_scan_log
    from octolgp.sim.scenes import simulate_paper2d

    data = simulate_paper2d(seed=args.seed)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise OctolgpError(f"--out must end in .npz, got {str(out)!r}")
    check_outputs(args.overwrite, out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with replacing(out) as tmp:  # never half a file at --out
        save_scan_log(tmp, data.scans, data.truth_points, data.truth_labels)
    n = sum(len(s) for s in data.scans)
    print(
        f"wrote {out}: {len(data.scans)} scans, {n} beams, {data.truth_points.shape[0]} test points"
    )
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    """``octolgp bench paper2d``: reproduce the paper's Table II and Fig. 2-4 in ``--out``."""
    from octolgp.bench.paper2d import format_table, run_paper2d

    out = Path(args.out)
    result = run_paper2d(out, seed=args.seed, repeats=args.repeats, n_seeds=args.seeds)
    table = format_table(result)
    print(table)
    (out / "table2.txt").write_text(table + "\n")
    print(f"\nwrote {out}/table2.txt, fig3_maps.png, fig4_roc.png, fig2_1d.png")
    return 0


def _build_with_progress(
    scan_list: list[Any], config: Any, path: Path, args: argparse.Namespace
) -> Any:
    """Build ``--method``'s map file at ``path`` with a progress bar in leaves."""
    from tqdm import tqdm

    from octolgp.batch.leafmap import build_tiled
    from octolgp.batch.voxelized import build_voxelized

    bar = tqdm(total=0, unit="leaf", disable=args.quiet or None, dynamic_ncols=True)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        if args.method == "leaf":
            return build_tiled(
                scan_list,
                config,
                path=path,
                scheduler=args.scheduler,
                workers=args.workers,
                n_jobs=args.jobs,
                progress=progress,
            )
        return build_voxelized(
            scan_list,
            config,
            args.method,
            path=path,
            progress=progress,
            scheduler=args.scheduler,
            n_jobs=args.jobs,
        )
    finally:
        bar.close()


def cmd_build(args: argparse.Namespace) -> int:
    """``octolgp build``: batch-build a map file from a whole log, each leaf fitted once."""
    import itertools

    from octolgp.batch.build import SCHEDULED
    from octolgp.cli.configs import check_config_output, config_path, resolve_config, write_config
    from octolgp.export.common import SQLITE_SIDECARS, replacing
    from octolgp.persist.mapfile import check_output

    out = Path(args.out)
    config_file = config_path(out)
    if args.method not in SCHEDULED and args.scheduler is not None:
        raise OctolgpError(
            f"--scheduler runs --method {' or '.join(SCHEDULED)} only, got --method {args.method}"
        )
    check_outputs(args.overwrite, out)
    first, scans = first_and_rest(args.scans, args.format, args.skip_bad)
    scan_list = list(itertools.islice(scans, args.limit))
    if args.downsample is not None:
        scan_list = [s.downsample(args.downsample) for s in scan_list]
    config = resolve_config(args, first.dim)
    check_scans(scan_list, config, f"SCANS {args.scans!r}")
    check_config_output(args.overwrite, config_file, args.config, config)
    check_output(out, overwrite=True)  # never a map another writer holds
    scheduler = args.scheduler
    if not args.quiet:
        where = "this process" if scheduler is None else f"Dask ({scheduler})"
        print(f"building {len(scan_list)} scans in {where} ...", file=sys.stderr, flush=True)
    # build beside the target and rename at the end: a killed build leaves no half map
    with replacing(out, sidecars=SQLITE_SIDECARS) as partial:
        m = _build_with_progress(scan_list, config, partial, args)
        stats = m.build_stats
        m.close()
    write_config(config, config_file, args.config)
    print(
        f"wrote {out}: {len(scan_list)} scans, {int(stats['items'])} training items, "
        f"{int(stats['leaves'])} leaves, {int(stats['voxels'])} voxels in "
        f"{stats['training'] + stats['assign'] + stats['fit'] + stats['store']:.1f} s "
        f"(fit {stats['fit']:.1f} s); config in {config_file}"
    )
    return 0


def _check_eval_numbers(args: argparse.Namespace) -> None:
    """Reject a ``--fraction`` outside (0, 1) and a ``--short`` that is negative or not finite."""
    if not (0.0 < args.fraction < 1.0):
        raise OctolgpError(f"--fraction must be in (0, 1), got {args.fraction}")
    if not (args.short >= 0.0 and args.short < float("inf")):
        raise OctolgpError(f"--short must be a finite number >= 0, got {args.short}")


def _draw_report(report: Any, out: Path, name: str) -> list[str]:
    """Draw the report's pictures in ``out``; return their file names.

    ``roc.png`` always; with an example map, ``errors.png`` and, for a 2D map, ``map.png``.
    """
    from octolgp.bench.evaluation import plot_errors, plot_roc
    from octolgp.export.image import write_png

    plot_roc(report, out / "roc.png", title=f"{name}: held-out scans")
    pictures = ["roc.png"]
    example = report.example
    if example is not None and example.centres.shape[0]:  # the map and its errors
        plot_errors(example, out / "errors.png", title=f"{name}, {example.split}: held-out errors")
        pictures.append("errors.png")
        if example.centres.shape[1] == 2:
            write_png(out / "map.png", example.centres, example.prob, example.resolution)
            pictures.append("map.png")
    return pictures


def cmd_eval(args: argparse.Namespace) -> int:
    """``octolgp eval``: held-out-scan ROC AUC of every method; roc.png, results.json, table.md."""
    import itertools
    import json

    from octolgp.bench.evaluation import evaluate_log
    from octolgp.cli.configs import config_path, resolve_config, write_config

    _check_eval_numbers(args)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    first, scans = first_and_rest(args.scans, args.format, args.skip_bad)
    scan_list = list(itertools.islice(scans, args.limit))
    config = resolve_config(args, first.dim)

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
        protocol=args.protocol,
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_config(config, config_path(out, folder=True), args.config)
    name = Path(args.scans).name
    pictures = _draw_report(report, out, name)
    (out / "results.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    table = (
        f"{name}, {len(scan_list)} scans, resolution {config.resolution} m, "
        f"{args.protocol} protocol: " + report.table()
    )
    (out / "table.md").write_text(table + "\n")
    print(table)
    written = ", ".join(
        f"{out}/{f}" for f in [*pictures, "results.json", "table.md", "config.toml"]
    )
    print(f"\nwrote {written}")
    return 0
