"""Handing freed heap memory back to the operating system, and reading the process's RSS.

glibc's ``malloc`` keeps memory freed by a burst of large temporary arrays (the
hyperparameter learning's kernel blocks, say) in its arenas instead of returning it:
after the first large ``free`` its mmap threshold rises to 32 MiB, so later arrays
come from the heap, whose free pages stay resident. ``malloc_trim(0)`` releases them.
Elsewhere (musl, macOS, Windows) there is nothing to call and
:func:`release_free_memory` does nothing.

:func:`rss_mb`, :func:`peak_rss_mb` and :func:`reset_peak_rss` read Linux's
``/proc/self``: the peak there (``VmHWM``) is this process's own, where
``getrusage``'s ``ru_maxrss`` starts from the parent's RSS at ``fork`` (Linux carries it
across ``exec``), so a child of a large process would report the parent's size.
"""

from __future__ import annotations

import ctypes
import platform
import sys
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path


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


def _status_mb(field: str) -> float:
    """A ``/proc/self/status`` field in MB (kB / 1000); NaN where there is none."""
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        return float("nan")
    for line in lines:  # a few dozen lines
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1e3
    return float("nan")


def rss_mb() -> float:
    """The resident set size of this process now, MB (Linux; NaN elsewhere)."""
    return _status_mb("VmRSS")


def peak_rss_mb() -> float:
    """The peak resident set size of this process since start or :func:`reset_peak_rss`, MB."""
    return _status_mb("VmHWM")


def reset_peak_rss() -> bool:
    """Start :func:`peak_rss_mb` afresh from the current RSS (Linux 4.0+).

    Returns whether it could (writing ``5`` to ``/proc/self/clear_refs``).
    """
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True
