"""Clipping segments to axis-aligned boxes (leaf halo boxes, cluster boxes)."""

from __future__ import annotations

import numpy as np

from octolgp.scan import FloatArray


def clip_to_box(
    a: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Liang-Barsky clipping of segments ``a → b`` to the box ``[lo, hi]``.

    Parameters
    ----------
    a, b : ndarray of shape (n, d)
        Segment ends, metres.
    lo, hi : ndarray of shape (d,) or (n, d)
        Box corners, metres.

    Returns
    -------
    a_in, b_in : ndarray of shape (n, d)
        The clipped segments (meaningful where ``keep``).
    keep : ndarray of bool, shape (n,)
        Segments that cross the box with a positive length.
    """
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t0 = (lo - a) / d
        t1 = (hi - a) / d
    tmin = np.where(d != 0, np.minimum(t0, t1), np.where((a >= lo) & (a <= hi), -np.inf, np.inf))
    tmax = np.where(d != 0, np.maximum(t0, t1), np.where((a >= lo) & (a <= hi), np.inf, -np.inf))
    t_in = np.clip(tmin.max(axis=1), 0.0, 1.0)
    t_out = np.clip(tmax.min(axis=1), 0.0, 1.0)
    keep = t_out > t_in
    return a + t_in[:, None] * d, a + t_out[:, None] * d, keep
