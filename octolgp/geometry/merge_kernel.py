"""The union of two ascending key arrays and where each key went, by one compiled merge (numba).

Observing a scan ends by joining its voxels with a return and its voxels seen free (each
ascending, without repeats) into one ascending array, and placing each side's counts in
it. The numpy form sorts the concatenation and then binary-searches every key (n log n);
this loop walks both arrays once. The results are the same arrays
(``tests/test_merge_kernel.py``); without numba (:data:`AVAILABLE` false) the numpy form
serves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether the compiled merge can run (numba is installed; it is imported on first use)."""

IntArray = NDArray[np.int64]


def _merge(
    a: IntArray, b: IntArray, out: IntArray, at_a: IntArray, at_b: IntArray
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Merge ascending ``a`` and ``b`` into ``out``; each one's place there. Returns the size."""
    i = 0
    j = 0
    k = 0
    while i < a.size or j < b.size:
        if j >= b.size or (i < a.size and a[i] < b[j]):
            out[k] = a[i]
            at_a[i] = k
            i += 1
        elif i >= a.size or b[j] < a[i]:
            out[k] = b[j]
            at_b[j] = k
            j += 1
        else:  # the same key on both sides
            out[k] = a[i]
            at_a[i] = k
            at_b[j] = k
            i += 1
            j += 1
        k += 1
    return k


@functools.cache
def _compiled() -> Callable[..., int]:
    """The merge compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    out: Callable[..., int] = njit(cache=True, nogil=True)(_merge)
    return out


def merge_positions(a: IntArray, b: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """The ascending union of ``a`` and ``b`` and each one's keys' places in it.

    Parameters
    ----------
    a, b : ndarray of int64, shape (n,) and (m,)
        Ascending, no repeats within each.

    Returns
    -------
    union : ndarray of int64, shape (u,)
        Ascending, no repeats.
    at_a, at_b : ndarray of int64, shape (n,) and (m,)
        ``union[at_a] == a`` and ``union[at_b] == b``.

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled merge needs numba")
    a = np.ascontiguousarray(a, dtype=np.int64)
    b = np.ascontiguousarray(b, dtype=np.int64)
    out = np.empty(a.size + b.size, dtype=np.int64)
    at_a = np.empty(a.size, dtype=np.int64)
    at_b = np.empty(b.size, dtype=np.int64)
    k = _compiled()(a, b, out, at_a, at_b)
    return out[:k], at_a, at_b
