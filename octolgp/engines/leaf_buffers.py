"""Compiled reads and writes of the touched leaves' counts in their own buffers (numba).

A step's gather (:func:`octolgp.engines.lattice.gather_observations`) reads the stored
counts (and summed chord shares) of a few thousand (voxel, leaf) pairs spread over the
halo boxes of a few hundred leaves, and writes the new ones into fresh buffers of the
leaves that change. Stacking every touched leaf's halo box into one array first would
copy each box whole (tens of kB a leaf) to reach a few dozen of its cells; these loops
reach each leaf's cells where they are, through its buffer's address. The caller holds
every buffer for the duration of a call (the leaves' arrays are alive in its lists) and
gives C-contiguous ones of the stated sizes; a zero address stands for a leaf with no
such buffer (nothing stored: zero). Imported only where numba is installed
(:data:`octolgp.engines.gather_kernel.AVAILABLE`); the numpy form of the gather serves
otherwise.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, cast

import numba
import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import NDArray

IntArray = NDArray[np.int64]


def _as_pointer(typingctx: object, address: types.Type) -> object:  # pragma: no cover - compiled
    """Typing and code of :data:`_pointer`: an integer address as a ``void *``."""
    if not isinstance(address, types.Integer):
        return None

    def codegen(context: object, builder: Any, signature: object, args: list[object]) -> object:
        return builder.inttoptr(args[0], cgutils.voidptr_t)

    return types.voidptr(address), codegen


_pointer = cast(Callable[[int], Any], intrinsic(_as_pointer))
"""In compiled code: an integer address as a ``void *`` for ``numba.carray``."""
carray = numba.np.numpy_support.carray


@njit(cache=True, nogil=True)
def _address(array: np.ndarray) -> int:  # pragma: no cover - compiled
    """The address of an array's first element."""
    return array.ctypes.data


def addresses(arrays: Sequence[np.ndarray | None]) -> IntArray:
    """Each array's data address, 0 for ``None``.

    The arrays must stay alive (and unresized) for as long as the addresses are used.
    """
    return np.array([0 if a is None else _address(a) for a in arrays], dtype=np.int64)


@njit(cache=True, nogil=True)
def _unit_values(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    n_halo: int,
    counts_at: IntArray,
    chord_at: IntArray,
    h0: IntArray,
    f0: IntArray,
    w0: IntArray,
    seen: NDArray[np.bool_],
) -> bool:  # pragma: no cover - compiled; tested through unit_values
    """Each voxel's stored counts and sum from its pairs; False where two copies differ."""
    for i in range(voxel.size):
        v = voxel[i]
        j = inverse[i]
        h = 0
        f = 0
        w = 0
        if counts_at[j] != 0:
            counts = carray(_pointer(counts_at[j]), 2 * n_halo, dtype=np.uint8)
            h = counts[flat[i]]
            f = counts[n_halo + flat[i]]
        if chord_at[j] != 0:
            w = carray(_pointer(chord_at[j]), n_halo, dtype=np.uint16)[flat[i]]
        if seen[v]:
            if h0[v] != h or f0[v] != f or w0[v] != w:
                return False
        else:
            seen[v] = True
            h0[v] = h
            f0[v] = f
            w0[v] = w
    return True


def unit_values(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    n_halo: int,
    counts_at: IntArray,
    chord_at: IntArray,
    n: int,
) -> tuple[IntArray, IntArray, IntArray] | None:
    """Each observed voxel's stored counts and summed chord shares, read from its pairs.

    Parameters
    ----------
    voxel, inverse, flat : ndarray of int64, shape (p,)
        Per (voxel, leaf) pair: its voxel, in ``[0, n)``, its leaf among the touched
        ones and its flat index in the leaf's halo box.
    n_halo : int
        Voxels of a halo box.
    counts_at, chord_at : ndarray of int64, shape (touched,)
        Per leaf, the address of its counts (uint8, ``(2, n_halo)`` C order: returns,
        then frees) and of its sums (uint16, ``(n_halo,)``); 0 where it has none.
    n : int
        Observed voxels.

    Returns
    -------
    tuple of ndarray of int64, shape (n,), or None
        Each voxel's return count, free count and sum (0 for a voxel without pairs);
        ``None`` when two copies of a voxel differ.
    """
    h0 = np.zeros(n, dtype=np.int64)
    f0 = np.zeros(n, dtype=np.int64)
    w0 = np.zeros(n, dtype=np.int64)
    seen = np.zeros(n, dtype=bool)
    agree = _unit_values(voxel, inverse, flat, n_halo, counts_at, chord_at, h0, f0, w0, seen)
    return (h0, f0, w0) if agree else None


@njit(cache=True, nogil=True)
def _write_pairs(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    n_halo: int,
    counts_at: IntArray,
    chord_at: IntArray,
    hits: IntArray,
    frees: IntArray,
    sums: IntArray,
) -> None:  # pragma: no cover - compiled; tested through write_pairs
    """Each pair's voxel's new counts (and sum) into its leaf's buffers, where it has them."""
    for i in range(voxel.size):
        j = inverse[i]
        v = voxel[i]
        if counts_at[j] != 0:
            counts = carray(_pointer(counts_at[j]), 2 * n_halo, dtype=np.uint8)
            counts[flat[i]] = hits[v]
            counts[n_halo + flat[i]] = frees[v]
        if chord_at[j] != 0:
            carray(_pointer(chord_at[j]), n_halo, dtype=np.uint16)[flat[i]] = sums[v]


def write_pairs(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    n_halo: int,
    counts_at: IntArray,
    chord_at: IntArray,
    hits: IntArray,
    frees: IntArray,
    sums: IntArray | None,
) -> None:
    """Write each (voxel, leaf) pair's new counts and sum into the leaf's new buffers.

    ``counts_at`` / ``chord_at`` as for :func:`unit_values`, of the buffers to write
    (0: a leaf left as it is); ``hits``, ``frees`` and ``sums`` (``None``: no sums)
    per voxel, each below its buffer's saturation (255 and 65535).
    """
    zero = np.zeros(0, dtype=np.int64)
    if sums is None:
        chord_at = np.zeros_like(counts_at)
    _write_pairs(
        voxel,
        inverse,
        flat,
        n_halo,
        counts_at,
        chord_at,
        hits,
        frees,
        zero if sums is None else sums,
    )
