"""Argument checks and file output shared by the exporters (OctoMap, PLY, PCD, PNG)."""

from __future__ import annotations

import io
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError

FloatArray = NDArray[np.float64]
PathLike = str | os.PathLike[str]


def per_voxel(values: ArrayLike, count: int, name: str) -> NDArray[Any]:
    """Return ``values`` as a ``(count,)`` array, or raise naming ``name``."""
    v = np.asarray(values)
    if v.shape != (count,):
        raise OctolgpError(f"{name} must have shape ({count},), one per key, got {v.shape}")
    return v


def as_finite(values: ArrayLike, count: int, name: str) -> FloatArray:
    """Return ``values`` as ``(count,)`` finite float64, or raise naming ``name``."""
    v = per_voxel(values, count, name)
    if v.dtype.kind not in "biuf":
        raise OctolgpError(f"{name} must be real numbers, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise OctolgpError(f"{name} must be finite, got {int((~np.isfinite(v)).sum())} bad values")
    return v


def as_centres(centres: ArrayLike, dims: tuple[int, ...]) -> FloatArray:
    """Return ``centres`` as finite float64 of shape ``(k, d)``, ``d`` in ``dims``, or raise."""
    c = np.asarray(centres)
    if c.ndim != 2 or c.shape[1] not in dims or c.dtype.kind not in "biuf":
        raise OctolgpError(f"centres must be a real array of shape (k, {dims}), got {c.shape}")
    c = c.astype(np.float64)
    if not np.isfinite(c).all():
        raise OctolgpError("centres must be finite")
    return c


def as_prob(prob: ArrayLike, count: int) -> FloatArray:
    """Return ``prob`` as ``(count,)`` float64 in [0, 1], or raise."""
    p = as_finite(prob, count, "prob")
    if p.size and (p.min() < 0.0 or p.max() > 1.0):
        raise OctolgpError(f"prob must lie in [0, 1], got [{p.min():g}, {p.max():g}]")
    return p


def xyz_prob_body(centres: ArrayLike, prob: ArrayLike, *, binary: bool) -> tuple[int, bytes]:
    """Voxel centres and P(occupied) as float32 ``x y z prob`` records, the body PLY and PCD share.

    Parameters
    ----------
    centres : array_like of float, shape (k, 3) or (k, 2)
        Voxel centres in the world frame, metres; 2D centres get ``z = 0``.
    prob : array_like of float, shape (k,)
        P(occupied) per centre, in [0, 1].
    binary : bool
        Packed little-endian records, or one text row per point with 9 significant digits
        (which round-trip float32).

    Returns
    -------
    count : int
        ``k``, the number of records.
    body : bytes

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value, or ``prob`` outside [0, 1].
    """
    c = as_centres(centres, (2, 3))
    p = as_prob(prob, c.shape[0])
    if c.shape[1] == 2:
        c = np.column_stack([c, np.zeros(c.shape[0])])
    record = np.empty(c.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("prob", "<f4")])
    for axis, name in enumerate("xyz"):
        record[name] = c[:, axis]
    record["prob"] = p
    if binary:
        return c.shape[0], record.tobytes()
    text = io.StringIO()
    rows = np.column_stack([record[name] for name in ("x", "y", "z", "prob")])
    np.savetxt(text, rows, fmt="%.9g")
    return c.shape[0], text.getvalue().encode("ascii")


def write_bytes(path: PathLike, chunks: list[bytes]) -> None:
    """Write ``chunks`` to ``path``; an OS failure raises :class:`OctolgpError`."""
    try:
        with open(path, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
    except OSError as exc:
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be written: {exc}") from exc
