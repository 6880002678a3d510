"""Log scans to a Rerun recording as a robot would, with an exact copy for replay.

:func:`log_scan` logs one scan per call, on the ``scan`` sequence timeline (and on the ``time``
timestamp timeline, in seconds since the epoch, when the scan has a stamp):

- ``{prefix}`` (default ``world/sensor``): ``Transform3D(translation, mat3x3=I)``, the sensor
  pose. Our scans carry no heading, so the sensor frame is world-aligned and centred on the
  origin (a 2D origin is padded with ``z = 0``).
- ``{prefix}/points``: ``Points3D`` (3D scan) or ``Points2D`` (2D scan), the endpoints in the
  sensor frame, ``points - origin``. Rerun stores positions as float32. The same row carries
  ``octolgp.ScanDisplay:exact`` (:data:`~octolgp.io.rrd_format.DISPLAY_MARK`): this display
  copy has an exact copy, so a reader never replays the scan from it.
- ``octolgp/scan``: the exact scan, as the dynamic archetype ``octolgp.Scan`` with float64
  components ``origin`` ``(d,)``, ``points`` ``(n*d,)`` (row-major), ``max_range`` and ``stamp``
  (NaN when absent), int64 ``dim``, and uint32 ``crc32``, the CRC-32 of all of them and of the
  scan's index (:func:`~octolgp.io.rrd_format.scan_checksum`). This copy is what makes a
  replay bit-identical; the checksum is what tells a corrupt copy from a good one.

:mod:`octolgp.io.rrd_read` reads such recordings (and any other) back. rerun is imported when
:func:`log_scan` is first called, not with this module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from octolgp.io.rrd_format import (
    CHECKSUM_COMPONENT,
    DISPLAY_ARCHETYPE,
    SCAN_ARCHETYPE,
    SCAN_ENTITY,
    SCAN_TIMELINE,
    TIME_TIMELINE,
    scan_checksum,
)
from octolgp.scan import Scan

if TYPE_CHECKING:
    import rerun as rr

__all__ = ["log_scan"]

_IDENTITY3 = np.eye(3)
_IDENTITY3.setflags(write=False)
_EXACT = np.ones(1, dtype=np.int64)
_EXACT.setflags(write=False)


def log_scan(
    rec: rr.RecordingStream, scan: Scan, index: int, *, prefix: str = "world/sensor"
) -> None:
    """Log one scan as a robot would, plus an exact copy (see the module docstring).

    Parameters
    ----------
    rec : rerun.RecordingStream
        The recording, with its sink already set (``rec.save(path)``, a memory sink, ...).
    scan : Scan
        The scan, world frame.
    index : int
        Its position in the sequence: the value on the ``scan`` timeline.
    prefix : str
        Entity of the sensor; the points go to ``{prefix}/points``.
    """
    import rerun as rr

    rec.set_time(SCAN_TIMELINE, sequence=index)
    if scan.stamp is None:
        rec.disable_timeline(TIME_TIMELINE)
    else:
        rec.set_time(TIME_TIMELINE, timestamp=scan.stamp)
    translation = np.zeros(3)
    translation[: scan.dim] = scan.origin
    rec.log(prefix, rr.Transform3D(translation=translation, mat3x3=_IDENTITY3))
    local = scan.points - scan.origin
    rec.log(
        f"{prefix}/points",
        rr.Points3D(local) if scan.dim == 3 else rr.Points2D(local),
        rr.DynamicArchetype(DISPLAY_ARCHETYPE, components={"exact": _EXACT}),
    )
    nan = np.nan
    components = {
        "origin": scan.origin,
        "points": scan.points.reshape(-1),
        "dim": np.array([scan.dim], dtype=np.int64),
        "max_range": np.array([nan if scan.max_range is None else scan.max_range]),
        "stamp": np.array([nan if scan.stamp is None else scan.stamp]),
    }
    crc = scan_checksum(index, **components)
    components[CHECKSUM_COMPONENT] = np.array([crc], dtype=np.uint32)
    rec.log(SCAN_ENTITY, rr.DynamicArchetype(SCAN_ARCHETYPE, components=components))
