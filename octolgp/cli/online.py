"""The online commands: ``run`` (a scan log) and ``replay`` (a Rerun recording).

Both insert scans one at a time into a new (or resumed) map file, configured by
:func:`octolgp.cli.configs.resolve_config` (``--config`` and the flags; the resolved config is
written beside the map as ``MAP.octolgp.toml``), optionally streaming the mapping to Rerun
(``--rerun-save/--rerun-connect/--rerun-serve/--rerun-web``, opened by
:func:`octolgp.sinks.rerun.open_recording` with the default blueprint; a served map is served
until Ctrl-C). Heavy modules are imported inside the commands.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from octolgp.cli.scans import first_and_rest, refused_scan, scan_total
from octolgp.errors import OctolgpError

if TYPE_CHECKING:
    from octolgp.scan import Scan

__all__ = ["cmd_replay", "cmd_run"]


def _recording(args: argparse.Namespace, dim: int) -> tuple[Any, str | None]:
    """The Rerun recording the options ask for and the URL it is served at, or ``None``s.

    rerun is imported only when a ``--rerun-*`` target is given.
    """
    web = getattr(args, "rerun_web", False)
    if not (args.rerun_save or args.rerun_connect or args.rerun_serve or web):
        return None, None
    from octolgp.sinks.rerun import default_blueprint, open_recording

    bp = default_blueprint(dim, uncertainty=args.rerun_uncertainty)
    ports: dict[str, Any] = {
        "grpc_port": getattr(args, "rerun_port", None),
        "web_port": getattr(args, "rerun_web_port", None),
    }
    try:
        if args.rerun_save:
            where = "--rerun-save"
            rec, url = open_recording("octolgp", save=args.rerun_save, blueprint=bp)
        elif args.rerun_connect:
            where = "--rerun-connect"
            rec, url = open_recording("octolgp", connect=args.rerun_connect, blueprint=bp)
        elif web:
            where = "--rerun-web"
            rec, url = open_recording("octolgp", web=True, blueprint=bp, **ports)
        else:
            where = "--rerun-serve"
            rec, url = open_recording("octolgp", serve=True, blueprint=bp, **ports)
    except OctolgpError as exc:
        raise OctolgpError(f"{where}: {exc}") from None
    if web:
        print(f"serving rerun's web viewer at {url} (open it in a browser)", flush=True)
    elif url is not None:
        print(f"serving the recording at {url} (open it with: rerun --connect {url})", flush=True)
    return rec, url


def _sink(rec: Any, args: argparse.Namespace) -> Any:
    """The Rerun sink of ``run``'s recording, with the ``--rerun-*`` options."""
    from octolgp.sinks.rerun import RerunSink

    return RerunSink(
        rec,
        rays=args.rerun_rays,
        uncertainty=args.rerun_uncertainty,
        colors=args.rerun_colors,
        free_voxels=args.rerun_free_voxels,
        blueprint=False,  # the recording has the CLI's default blueprint
        follow=True,  # which the sink bounds on the map as it grows
    )


def _reopen(out: Path, config: Any, config_file: Path, given: str | None) -> Any:
    """The map file ``out`` reopened for ``--resume``, checked against the scans' config.

    Its own config is written beside it (``given``: the ``--config`` file, never rewritten).
    """
    from octolgp.cli.configs import write_config
    from octolgp.mapping.online import OnlineMap

    m = OnlineMap.open(out)
    if m.config.dim != config.dim or m.config.resolution != config.resolution:
        m.close()
        raise OctolgpError(
            f"--resume: {str(out)!r} is a {m.config.dim}D map at {m.config.resolution:g} m, "
            f"the scans are {config.dim}D and --resolution is {config.resolution:g} m"
        )
    try:
        write_config(m.config, config_file, given)
    except OctolgpError:
        m.close()
        raise
    return m


def _after_journal(m: Any, scans: Iterator[Any], out: Path, source: str) -> Iterator[Any]:
    """The scans after those ``m`` journaled, once the log is checked to begin with them.

    ``source`` names the log in messages (``SCANS 'intel.log'``). The map is closed when
    the check fails.

    Raises
    ------
    OctolgpError
        If the map keeps no journal, the log is shorter than the journal, or the log's
        first scans are not the journaled ones (origins and points compared exactly, the
        log's rounded as the map rounds what it inserts).
    """
    try:
        return _check_journal(m, iter(scans), out, source)
    except BaseException:
        m.close()
        raise


def _check_journal(m: Any, scans: Iterator[Any], out: Path, source: str) -> Iterator[Any]:
    """:func:`_after_journal`, leaving the map open."""
    import numpy as np

    from octolgp.mapping.evidence import map_scans

    n = start = m.journal_start  # a journal that keeps the latest scans begins later
    for _ in range(start):  # one iteration per scan folded out of the journal
        if next(scans, None) is None:
            raise OctolgpError(
                f"--resume: {source} holds fewer scans than {str(out)!r} ({m.n_scans}): the "
                "map was built from another log"
            )
    for n, mine in enumerate(m.scans(), start=start + 1):  # one iteration per journaled scan
        theirs = next(scans, None)
        if theirs is not None:
            theirs = map_scans([theirs], m.config)[0]
        if theirs is None:
            raise OctolgpError(
                f"--resume: {source} holds {n - 1} scans, {str(out)!r} {m.n_scans}: the map "
                "was built from another log"
            )
        if not (
            np.array_equal(theirs.origin, mine.origin)
            and np.array_equal(theirs.points, mine.points)
        ):
            raise OctolgpError(
                f"--resume: scan {n} of SCANS is not scan {n} of {str(out)!r} ({source}): the "
                "map was built from another log (or a log filtered another way)"
            )
    if n != m.n_scans:  # a journal holds every scan or none
        raise OctolgpError(
            f"--resume: {str(out)!r} keeps no journal of its {m.n_scans} scans (saved from "
            f"memory by an older version), so it cannot be checked against {source}"
        )
    return scans


PROGRESS_SECONDS = 10.0
"""Seconds between progress lines when stderr is not a terminal (a pipe, a CI log)."""


def progress_line(done: int, total: int | None, seconds: float, leaves: int) -> str:
    """One progress line: scans done (of ``total``), rate, ETA where the total is known."""
    rate = done / seconds if seconds > 0 else float("nan")
    of = f"{done}" if total is None else f"{done}/{total} ({100 * done / max(total, 1):.0f}%)"
    eta = ""
    if total is not None and rate > 0:
        left = max(total - done, 0) / rate
        eta = f", ETA {int(left // 60)}:{int(left % 60):02d}"
    return f"octolgp: scan {of}, {rate:.1f} scans/s{eta}, {leaves} leaves"


def _insert_all(
    m: Any, scans: Iterator[Any], quiet: bool, source: str, total: int | None = None
) -> int:
    """Insert the scans one by one, then flush the bootstrap.

    Progress: a bar on a terminal (scans/s, and with ``total`` the share and ETA), else a
    line every :data:`PROGRESS_SECONDS`; ``quiet``: none. A refused scan is named by its
    number in the log and ``source`` (``SCANS 'x.log'``). Returns the kernel matrices
    repaired by jitter.
    """
    from tqdm import tqdm

    terminal = sys.stderr.isatty()
    bar = tqdm(scans, unit="scan", total=total, disable=quiet or not terminal, dynamic_ncols=True)
    repaired, t0, said = 0, time.monotonic(), time.monotonic()
    for i, scan in enumerate(bar, start=1):  # one iteration per scan
        try:
            update = m.insert_scan(scan)
        except OctolgpError as exc:
            raise refused_scan(source, m.n_scans + 1, exc) from None
        repaired += update.repaired
        bar.set_postfix(leaves=update.n_leaves, refit=update.refit_leaves, refresh=False)
        if not quiet and not terminal and time.monotonic() - said >= PROGRESS_SECONDS:
            said = time.monotonic()
            print(progress_line(i, total, said - t0, update.n_leaves), file=sys.stderr)
    last = m.flush()
    return repaired + (0 if last is None else last.repaired)


def _map_scans(
    scans: Iterator[Any],
    first: Any,
    args: argparse.Namespace,
    source: str,
    total: int | None = None,
) -> int:
    """Insert scans one by one into a new map file (progress bar in scans/s).

    ``source`` names the log in messages (``SCANS 'intel.log'``).
    """
    import itertools

    from octolgp.cli.configs import (
        check_config_output,
        check_outputs,
        config_path,
        resolve_config,
        write_config,
    )
    from octolgp.mapping.online import OnlineMap
    from octolgp.persist.mapfile import check_output

    out = Path(args.out)
    resume = getattr(args, "resume", False) and out.exists()
    if out.exists() and not (args.overwrite or resume):
        raise OctolgpError(
            f"--out {str(out)!r} already exists (pass --resume to continue it, "
            "--overwrite to replace it)"
        )
    if args.rerun_save:
        check_outputs(args.overwrite, Path(args.rerun_save), what="--rerun-save")
    config = resolve_config(args, first.dim, n_jobs=args.jobs)
    config_file = config_path(out)
    if not resume:
        check_config_output(args.overwrite, config_file, args.config, config)
        check_output(out, overwrite=True)  # never a map another writer holds
        write_config(config, config_file, args.config)
    rec, url = _recording(args, config.dim)
    sink = None if rec is None else _sink(rec, args)
    if resume:
        m = _reopen(out, config, config_file, args.config)
        m.sink = m.sink if sink is None else sink
        scans = _after_journal(m, scans, out, source)
        if args.limit is not None:  # --limit counts the log's scans, those journaled too
            scans = itertools.islice(scans, max(0, args.limit - m.n_scans))
        print(f"resuming {out} after {m.n_scans} scans")
    else:
        if args.limit is not None:
            scans = itertools.islice(scans, args.limit)
        for suffix in ("", "-wal", "-shm"):
            Path(str(out) + suffix).unlink(missing_ok=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        m = OnlineMap(config, path=out, sink=sink)
    try:
        with m:
            repaired = _insert_all(m, scans, args.quiet, source, None if resume else total)
            n_leaves, n_scans = len(m.store), m.n_scans
    except BaseException:
        if rec is not None:
            rec.flush()
            rec.disconnect()
        raise
    print(f"wrote {out}: {n_scans} scans, {n_leaves} leaves, hyperparameters {m.hyperparameters}")
    print(f"wrote {config_file}: the resolved config")
    if repaired:
        print(
            f"note: {repaired} leaf kernel matrices were not positive definite; repaired by jitter"
        )
    if rec is not None:
        rec.flush()
        if url is not None:  # --rerun-serve/--rerun-web: viewers can still look at the map
            from octolgp.sinks.rerun import serve_until_interrupted

            serve_until_interrupted(url)
        rec.disconnect()
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """``octolgp run``: map a scan log online, scan by scan."""
    names = ("scan_topic", "pose_topic", "frame")
    bag = {k: getattr(args, k) for k in names if getattr(args, k) is not None}
    first, scans = first_and_rest(args.scans, args.format, args.skip_bad, args.kitti_frame, bag)
    if args.max_range is not None or args.downsample is not None:
        scans = (prepared(s, args.max_range, args.downsample) for s in scans)
    total = None if args.quiet else scan_total(args.scans, args.format, args.limit)
    return _map_scans(scans, first, args, f"SCANS {args.scans!r}", total)


def prepared(scan: Scan, max_range: float | None, downsample: float | None) -> Scan:
    """A scan as ``run --max-range --downsample`` inserts it.

    ``max_range`` lowers the scan's no-return range (beams at least that long are
    no-returns, their points kept); ``downsample`` keeps one beam per voxel of that edge
    (:meth:`~octolgp.Scan.downsample`), after the no-return range is set.
    """
    from octolgp.scan import Scan

    if max_range is not None:
        reach = max_range if scan.max_range is None else min(scan.max_range, max_range)
        scan = Scan(scan.origin, scan.points, reach, scan.stamp, scan.rotation)
    return scan if downsample is None else scan.downsample(downsample)


def cmd_replay(args: argparse.Namespace) -> int:
    """``octolgp replay``: rebuild a map from the scans of a Rerun recording; prints its notes."""
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
    source = f"recording {args.recording!r}"
    status = _map_scans(itertools.chain([first], it), first, args, source)
    for note in getattr(reader, "notes", []):
        print(f"note: {note}")
    return status
