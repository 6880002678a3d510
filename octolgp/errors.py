"""The one exception type that every rejected input raises."""

from __future__ import annotations


class OctolgpError(ValueError):
    """A rejected input: a bad config value, array, file or argument.

    The message names the offending field (for example ``Scan.points`` or
    ``MapConfig.resolution``). A subclass of :class:`ValueError` so that generic
    callers can catch it as one.
    """


class MapFileNotFound(OctolgpError, FileNotFoundError):  # noqa: N818 - name from docs/api.md
    """A map, scan log or recording path that does not exist."""
