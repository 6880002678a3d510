"""The one-writer rule of a map file: an exclusive ``flock`` on the file itself.

A writer holds the lock from opening the file until after its SQLite connection is
closed, so a second writer (another process, or another map object in this one)
is refused at once instead of interleaving transactions. Readers take no lock:
they read a snapshot (one SQLite read transaction) beside a writer.

``flock`` locks are independent of the POSIX record locks SQLite takes on the same
file on Linux and the BSDs. POSIX record locks are dropped when *any* descriptor of
the file is closed, so the lock's descriptor is closed only after the connection
is. Where ``fcntl`` is missing (Windows) the rule is not enforced.
"""

from __future__ import annotations

import os
from pathlib import Path

from octolgp.errors import OctolgpError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]


class WriterLock:
    """An exclusive, non-blocking lock on a map file, held until :meth:`release`.

    Parameters
    ----------
    path : Path
        The map file.
    create : bool
        Create the file (it must not exist; ``O_EXCL``, so two creators never
        share a file).

    Raises
    ------
    OctolgpError
        If the file exists when creating, cannot be opened for writing, or another
        writer holds it.
    """

    def __init__(self, path: Path, *, create: bool = False) -> None:
        flags = os.O_RDWR | (os.O_CREAT | os.O_EXCL if create else 0)
        try:
            self._fd: int | None = os.open(path, flags, 0o644)
        except FileExistsError:
            raise OctolgpError(
                f"path {str(path)!r} already exists; reopen it with OnlineMap.open or remove it"
            ) from None
        except PermissionError:
            raise OctolgpError(
                f"map file {str(path)!r} is read-only here; open it with "
                "OnlineMap.open(path, read_only=True) to read it"
            ) from None
        except OSError as exc:
            raise OctolgpError(f"map file {str(path)!r} cannot be opened: {exc}") from None
        if fcntl is None:  # pragma: no cover - Windows
            return
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            self._fd = None
            raise OctolgpError(
                f"map file {str(path)!r} is open for writing elsewhere (one writer per map "
                "file); close that map first, or open this one with read_only=True"
            ) from None

    def release(self) -> None:
        """Drop the lock (after the file's SQLite connection is closed)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def held_by_a_writer(path: Path) -> bool:
    """Whether a writer holds the map file ``path`` now (``False`` if it cannot tell)."""
    if fcntl is None:  # pragma: no cover - Windows
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing also releases a lock taken just now
    return False
