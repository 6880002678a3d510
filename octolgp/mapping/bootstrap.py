"""The learning bootstrap: scans buffered until the hyperparameters are learnt.

A map made with ``MapConfig.hyperparameters=None`` buffers its first
``online.learn_scans`` scans, learns the hyperparameters on them
(:func:`octolgp.gp.learning.learn_hyperparameters`) and then holds them fixed. While
scans are buffered, reads answer *provisionally*: from a map fitted on the buffered
scans with hyperparameters learnt on them, built for the read and thrown away when the
next scan arrives. Reads never end the bootstrap, so the map after k scans is a function
of those k scans and the config only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping
from typing import Generic, TypeVar

from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.learning import learn_hyperparameters
from octolgp.scan import Scan
from octolgp.training import config_beams, stack_beams

M = TypeVar("M")


class Bootstrap(Generic[M]):
    """The scans awaiting the hyperparameters, and the provisional map of them.

    Parameters
    ----------
    config : MapConfig
        The map's resolved config.
    scans : iterable of Scan
        Scans already buffered (a reopened map's journal).
    """

    def __init__(self, config: MapConfig, scans: Iterable[Scan] = ()) -> None:
        self.config = config
        self.scans: list[Scan] = list(scans)
        self._provisional: tuple[int, M] | None = None

    def __len__(self) -> int:
        return len(self.scans)

    def add(self, scan: Scan) -> bool:
        """Buffer a scan; whether the buffer now holds ``learn_scans`` scans."""
        self.scans.append(scan)
        self._provisional = None
        return len(self.scans) >= self.config.learn_scans

    def can_learn(self) -> bool:
        """Whether the buffered scans hold data to learn from: a return at least.

        Free segments alone (scans whose beams are all no-returns) say nothing of what
        is occupied, so the map keeps buffering until a return arrives.
        """
        for scan in self.scans:  # stops at the first scan with a return
            origins, ends, max_range = stack_beams([scan])
            if config_beams(origins, ends, max_range, self.config).is_hit.any():
                return True
        return False

    def learn(self) -> Hyperparameters:
        """The hyperparameters learnt on the buffered scans (nothing changes)."""
        return learn_hyperparameters(self.scans, self.config)

    def take(self) -> list[Scan]:
        """Empty the buffer; return the scans it held, in order."""
        scans, self.scans, self._provisional = self.scans, [], None
        return scans

    def restore(self, scans: list[Scan]) -> None:
        """Put back the buffer as it was before a step that failed."""
        same = len(scans) == len(self.scans)
        if not same or any(a is not b for a, b in zip(scans, self.scans, strict=True)):
            self.scans, self._provisional = list(scans), None

    def corrected(self, scans: Mapping[int, Scan]) -> None:
        """Replace buffered scans by number (from 1) with their corrected versions."""
        self.scans = [scans.get(i, s) for i, s in enumerate(self.scans, start=1)]
        self._provisional = None

    def provisional(self, build: Callable[[MapConfig, list[Scan]], M]) -> M:
        """The provisional map of the buffer, built by ``build(config, scans)`` once per buffer.

        ``config`` has no memory budget and either learnt hyperparameters or, when the
        buffer holds no training data yet, none (``build`` then gets no scans).
        """
        if self._provisional is None or self._provisional[0] != len(self.scans):
            config = dataclasses.replace(self.config, memory_budget_mb=None)
            scans: list[Scan] = []
            if self.can_learn():
                config = dataclasses.replace(config, hyperparameters=self.learn())
                scans = self.scans
            self._provisional = (len(self.scans), build(config, scans))
        return self._provisional[1]
