"""Handing freed heap memory back to the operating system.

glibc's ``malloc`` keeps memory freed by a burst of large temporary arrays (the
hyperparameter learning's kernel blocks, say) in its arenas instead of returning it:
after the first large ``free`` its mmap threshold rises to 32 MiB, so later arrays
come from the heap, whose free pages stay resident. ``malloc_trim(0)`` releases them.
Elsewhere (musl, macOS, Windows) there is nothing to call and
:func:`release_free_memory` does nothing.
"""

from __future__ import annotations

import ctypes
import platform
import sys
from collections.abc import Callable
from functools import lru_cache


@lru_cache(maxsize=1)
def _malloc_trim() -> Callable[[int], int] | None:
    """The C library's ``malloc_trim``, or ``None`` where it is not glibc."""
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return None
    try:
        trim = ctypes.CDLL(None).malloc_trim  # the C library this process already runs
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc ``malloc_trim(0)``).

    Cheap (it walks the free lists, a few milliseconds at most) and safe from any
    thread; it frees nothing that is in use, so it never changes a result, only the
    resident set size.

    Returns
    -------
    bool
        Whether memory was released: ``False`` when glibc had none to give back or
        the C library is not glibc (a no-op there).
    """
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
