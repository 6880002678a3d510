"""What every streaming scan reader shares: a one-pass iterator over its own generator."""

from __future__ import annotations

from collections.abc import Generator
from typing import Self

from octolgp.scan import Scan

__all__ = ["ScanStream"]


class ScanStream:
    """A one-pass iterator of :class:`~octolgp.scan.Scan`.

    A reader sets ``self._scans`` to its generator (usually ``self._generate()``, which
    reads nothing until the first ``next``); iteration and :meth:`close` go through it.
    """

    _scans: Generator[Scan, None, None]

    def __iter__(self) -> Self:
        return self

    def __next__(self) -> Scan:
        return next(self._scans)

    def close(self) -> None:
        """Stop reading and close the file being read."""
        self._scans.close()
