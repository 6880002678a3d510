"""Which way the robot faces, from what a scan carries: its pose, its beams, else its motion.

A :class:`~octolgp.scan.Scan` holds the sensor's position and world-frame endpoints,
and its orientation where the reader knew it (``Scan.rotation``). The Rerun view's
heading arrow is, in that order:

0. **Orientation.** The sensor's forward axis (the rotation's first column) where the
   scan carries its rotation.
1. **Field of view.** A sensor that sees less than all round (a forward-facing planar
   laser, as the Intel log's 180° one) leaves a gap of at least :data:`BLIND_DEGREES`
   in its beams' azimuths (about the world's ``z`` in 3D); the heading is the middle of
   the beams' span, which is the pose's yaw for a field of view symmetric about it.
2. **Motion.** An all-round sensor (a spinning lidar) shows no front: the heading is
   the direction of travel since the last position at least :data:`MIN_STEP` metres
   away (in 3D with its climb), and stays put while the robot stands or turns in place.
"""

from __future__ import annotations

import numpy as np

from octolgp.scan import FloatArray, Scan

__all__ = ["BLIND_DEGREES", "MIN_STEP", "Heading", "view_direction"]

BLIND_DEGREES = 90.0
"""A gap in the beams' azimuths at least this wide is the back of a sensor that faces forward."""
MIN_STEP = 0.1
"""Metres the robot moves before its direction of travel is taken as its heading."""
_BINS = 72  # azimuth bins (5°) in which a gap is looked for
_MOST_BEAMS = 4096  # beams looked at per scan (every k-th beam of a larger scan)


def view_direction(scan: Scan) -> FloatArray | None:
    """Unit vector (``scan.dim``,) of the middle of the scan's field of view, or ``None``.

    ``None`` when the beams' azimuths leave no gap of :data:`BLIND_DEGREES` (an all-round
    sensor) or no beam leaves the origin. In 3D the vector is horizontal.
    """
    step = max(1, len(scan) // _MOST_BEAMS)
    rel = scan.points[::step, :2] - scan.origin[:2]
    rel = rel[np.einsum("ij,ij->i", rel, rel) > 1e-18]
    if rel.shape[0] == 0:
        return None
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    bins = np.floor((azimuth + np.pi) * (_BINS / (2 * np.pi))).astype(np.int64) % _BINS
    empty = np.bincount(bins, minlength=_BINS) == 0
    if not empty.any():
        return None
    # the longest circular run of empty bins: runs of the doubled sequence, capped at _BINS
    doubled = np.concatenate([empty, empty]).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], doubled, [0]])))
    starts, ends = edges[::2], edges[1::2]
    lengths = np.minimum(ends - starts, _BINS)
    longest = int(np.argmax(lengths))
    if (lengths[longest] + 2) * (360.0 / _BINS) < BLIND_DEGREES:  # a gap spans 2 bins more
        return None
    # exact span of the beams: turn the gap's middle to ±π, then the beams' extremes
    gap = -np.pi + (starts[longest] + 0.5 * lengths[longest]) * (2 * np.pi / _BINS)
    back = gap + np.pi
    turned = np.angle(np.exp(1j * (azimuth - back)))
    lo, hi = float(turned.min()), float(turned.max())
    if np.degrees(2 * np.pi - (hi - lo)) < BLIND_DEGREES - 1e-9:
        return None
    yaw = back + 0.5 * (lo + hi)
    out = np.zeros(scan.dim)
    out[:2] = np.cos(yaw), np.sin(yaw)
    return out


class Heading:
    """The heading of each scan in turn (:func:`view_direction`, else the motion)."""

    def __init__(self) -> None:
        self._moved_from: FloatArray | None = None
        self.direction: FloatArray | None = None

    def update(self, scan: Scan) -> FloatArray | None:
        """The unit heading of ``scan`` (``None`` until one is known); call once per scan."""
        seen = None if scan.rotation is None else np.asarray(scan.rotation[:, 0], dtype=float)
        if seen is None:
            seen = view_direction(scan)
        if self._moved_from is None:
            self._moved_from = scan.origin
        step = scan.origin - self._moved_from
        length = float(np.linalg.norm(step))
        if length >= MIN_STEP:
            self._moved_from = scan.origin
            if seen is None:
                seen = step / length
        if seen is not None:
            self.direction = seen
        return self.direction
