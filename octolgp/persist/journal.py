"""A journaled scan's points, compactly and exactly: the steps of a rounded scan.

A map with ``OnlineConfig.scan_precision`` is built from scans rounded to whole steps
from the sensor, their beams sorted by their steps (:meth:`octolgp.Scan.rounded`), so
the journal can keep the steps instead of the float64 points and still give back
exactly what the map was built from. The blob, before zlib:

- a header: the step in metres (float64), points ``n`` (uint32), kept points ``k``
  (uint32), bytes per step difference ``w`` (uint8: 2, 4 or 8, the fewest that hold
  them);
- a bitmap of the kept points (``np.packbits``, little bit order) and their
  coordinates (float64, ``k`` x d): points stored as given. Scans rounded by this
  version keep none (``k = 0``); files of version 5
  kept their no-return beams so;
- per axis, the differences of consecutive points' steps (the first from zero), in
  ``w``-byte integers, the bytes of each significance stored together (a byte
  shuffle): sorted beams have close steps, so the differences are small and most of
  their high bytes zero, which zlib packs tightly.

:func:`next_checkpoints` is the retention policy (``OnlineConfig.journal_scans``) that
a map file and the in-RAM journal of a map without one share.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.scan import FloatArray, Scan, points_from_steps, scan_steps

_HEAD = struct.Struct("<dIIB")


def _shuffled(diffs: np.ndarray, width: int) -> bytes:
    """The bytes of ``diffs`` (d, n) grouped by significance per axis."""
    d, n = diffs.shape
    raw = np.ascontiguousarray(diffs.astype(f"<i{width}")).view(np.uint8).reshape(d, n, width)
    return np.ascontiguousarray(raw.transpose(0, 2, 1)).tobytes()


def _unshuffled(blob: bytes, d: int, n: int, width: int) -> np.ndarray:
    """Inverse of :func:`_shuffled`: int64 differences, (d, n)."""
    raw = np.frombuffer(blob, np.uint8, d * n * width).reshape(d, width, n)
    out: np.ndarray = np.ascontiguousarray(raw.transpose(0, 2, 1)).view(f"<i{width}").reshape(d, n)
    return out.astype(np.int64)


def encode_points(scan: Scan, precision: float) -> bytes:
    """A rounded scan's points as a compact blob (see the module's docstring).

    ``scan`` must be rounded to ``precision`` (``scan.rounded(precision)``); its points
    then read back bit for bit (:func:`decode_points`).
    """
    diffs = np.diff(scan_steps(scan, precision).T, axis=1, prepend=0)
    top = int(np.abs(diffs).max(initial=0))
    width = next(w for w in (2, 4, 8) if top < 2 ** (8 * w - 1))
    parts = [
        _HEAD.pack(precision, len(scan), 0, width),
        np.packbits(np.zeros(len(scan), dtype=bool), bitorder="little").tobytes(),
        _shuffled(diffs, width),
    ]
    return zlib.compress(b"".join(parts), 6)


def decode_points(blob: bytes, origin: FloatArray, dim: int) -> FloatArray:
    """Inverse of :func:`encode_points`: the points, (n, d) float64.

    Raises
    ------
    OctolgpError
        On a blob that does not decompress or does not add up.
    """
    try:
        raw = zlib.decompress(blob)
    except zlib.error:
        raise OctolgpError("journaled points do not decompress") from None
    if len(raw) < _HEAD.size:
        raise OctolgpError("journaled points are truncated")
    precision, n, k, width = _HEAD.unpack_from(raw)
    n_bits = (n + 7) // 8
    if width not in (2, 4, 8) or not precision > 0 or k > n:
        raise OctolgpError("journaled points have a bad header")
    if len(raw) != _HEAD.size + n_bits + 8 * k * dim + dim * n * width:
        raise OctolgpError("journaled points have the wrong length")
    at = _HEAD.size
    bits = np.unpackbits(np.frombuffer(raw, np.uint8, n_bits, at), count=n, bitorder="little")
    kept = bits.astype(bool)
    at += n_bits
    if int(kept.sum()) != k:
        raise OctolgpError("journaled points have a bad header")
    kept_points = np.frombuffer(raw, "<f8", k * dim, at).reshape(k, dim)
    at += 8 * k * dim
    steps = np.cumsum(_unshuffled(raw[at:], dim, n, width), axis=1).T
    points = points_from_steps(origin, steps, precision)
    points[kept] = kept_points
    return points


def next_checkpoints(
    checkpoints: list[int], n_scans: int, window: int | None, learning: bool
) -> list[int]:
    """The checkpoints after a step: one every ``window`` scans, the older ones dropped.

    The journal keeps the scans after the first checkpoint returned: at least the
    latest ``window`` scans, at most about twice that. Nothing changes without a window
    (every scan journaled) or while the map learns (it learns on the journal).

    Parameters
    ----------
    checkpoints : list of int
        Before the step, ascending; the first is the journal's start.
    n_scans : int
        The map's scan count after the step.
    window : int or None
        ``OnlineConfig.journal_scans``.
    learning : bool
        The map has no hyperparameters yet.

    Returns
    -------
    list of int
        Ascending; scans up to the first are dropped from the journal, and the
        leaves kept as of earlier checkpoints with them.
    """
    out = list(checkpoints)
    if window is None or learning:
        return out
    if n_scans - out[-1] >= window:
        out.append(n_scans)
    start = max([c for c in out if c <= n_scans - window], default=out[0])
    return [c for c in out if c >= start]
