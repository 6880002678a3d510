"""Reading the SCANS argument of ``run``, ``build`` and ``eval``."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from octolgp.errors import OctolgpError

__all__ = ["check_scans", "first_and_rest", "refused_scan", "scan_total"]


def first_and_rest(
    path: str,
    fmt: str | None,
    skip_bad: bool = False,
    kitti_frame: str | None = None,
    bag: dict[str, str] | None = None,
) -> tuple[Any, Iterator[Any]]:
    """The first scan of a log (to learn its dimension) and an iterator over all of them.

    With ``skip_bad`` the reader skips malformed parts; once the iterator is exhausted a
    line on stderr says how many it skipped. ``kitti_frame`` (``"velodyne"`` or
    ``"cam0"``) picks a KITTI sequence's world frame; ``bag`` (``scan_topic``,
    ``pose_topic``, ``frame``: the flags given) a ROS bag's topics and fixed frame, and is
    refused for another format.
    """
    import itertools

    from octolgp.io import detect_format, load_scans, read_kitti, read_rosbag

    kind = fmt or (detect_format(Path(path)) if Path(path).exists() else None)
    if bag and kind != "rosbag":
        flags = ", ".join("--" + k.replace("_", "-") for k in bag)
        raise OctolgpError(f"{flags}: for ROS bags only; SCANS {path!r} is not one")
    if bag:
        reader: Any = read_rosbag(
            path,
            scan_topic=bag.get("scan_topic"),
            pose_topic=bag.get("pose_topic"),
            frame=bag.get("frame"),
            skip_bad=skip_bad,
        )
    elif kitti_frame is not None and kind == "kitti":
        reader = read_kitti(path, world=kitti_frame, skip_bad=skip_bad)
    else:
        reader = load_scans(path, format=kind, skip_bad=skip_bad)  # detected once
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


def scan_total(path: str, fmt: str | None, limit: int | None) -> int | None:
    """The scans a ``run`` will insert, where a quick count tells (CARMEN), for progress."""
    from octolgp.io import detect_format
    from octolgp.io.carmen import count_laser_lines

    try:
        total = count_laser_lines(path) if (fmt or detect_format(Path(path))) == "carmen" else None
    except (OSError, OctolgpError, EOFError):
        total = None  # the reader reports what is wrong with the file
    if total is None:
        return limit
    return total if limit is None else min(total, limit)


def refused_scan(source: str, number: int, exc: OctolgpError) -> OctolgpError:
    """The error for scan ``number`` (from 1) of a log a map refuses.

    ``source`` names the log (``SCANS 'intel.log'``): ``SCANS 'intel.log', scan 12: why``.
    """
    return OctolgpError(f"{source}, scan {number}: {exc}")


def check_scans(scans: list[Any], config: Any, source: str) -> None:
    """Check every scan as a map of ``config`` checks it, before a batch build.

    Raises
    ------
    OctolgpError
        For the first scan the map would refuse, by :func:`refused_scan`.
    """
    from octolgp.mapping.evidence import check_scan
    from octolgp.mapping.grid import LeafGrid

    grid = LeafGrid.from_config(config)
    for number, scan in enumerate(scans, start=1):  # one iteration per scan
        try:
            check_scan(scan, config, grid)
        except OctolgpError as exc:
            raise refused_scan(source, number, exc) from None
