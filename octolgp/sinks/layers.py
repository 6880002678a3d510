"""The Rerun view's map layers as plain arrays: 2D tiles of grey levels, 3D regions of boxes.

Each layer remembers what was last logged, so a step re-logs only the tiles or regions
whose content changed (:mod:`octolgp.sinks.rerun` logs them).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray

__all__ = ["Regions", "Tiles"]


@dataclass
class Tiles:
    """A 2D map as grey uint8 tiles, ``tile`` × ``tile`` cells each (row y, column x).

    ``cell`` coordinates are world voxel keys less the key offset: cell ``c`` covers
    ``[c r, (c + 1) r)`` metres. Leaves never straddle tiles (``tile`` is a multiple of
    the leaf side).
    """

    tile: int
    fill: int
    grey: dict[tuple[int, int], NDArray[np.uint8]] = field(default_factory=dict)
    logged: dict[tuple[int, int], NDArray[np.uint8]] = field(default_factory=dict)
    where: dict[int, tuple[tuple[int, int], int, int, int]] = field(default_factory=dict)
    dirty: set[tuple[int, int]] = field(default_factory=set)
    placed: set[tuple[int, int]] = field(default_factory=set)  # static transform logged

    def paint(self, keys: list[int], cells: NDArray[np.int64], grey: NDArray[np.uint8]) -> None:
        """Write leaves' grey levels: ``cells`` (n, 2) their lower corners, ``grey`` (n, s, s)."""
        side = grey.shape[1]
        tiles = cells // self.tile
        offsets = cells - tiles * self.tile
        steps = np.arange(side)
        unique, inverse = np.unique(tiles, axis=0, return_inverse=True)
        for k, (tx, ty) in enumerate(unique.tolist()):  # one iteration per tile written to
            t = (int(tx), int(ty))
            image = self.grey.get(t)
            if image is None:
                image = self.grey[t] = np.full((self.tile, self.tile), self.fill, np.uint8)
            mine = np.flatnonzero(inverse.reshape(-1) == k)
            rows = offsets[mine, 1, None, None] + steps[None, :, None]
            cols = offsets[mine, 0, None, None] + steps[None, None, :]
            image[rows, cols] = grey[mine]  # flat voxel order is x fastest: rows are y
            self.dirty.add(t)
            for i in mine.tolist():  # one iteration per leaf: where to erase it from
                self.where[keys[i]] = (t, int(offsets[i, 1]), int(offsets[i, 0]), side)

    def erase(self, key: int) -> None:
        """A leaf left the map: its cells turn back to the fill (unknown)."""
        placed = self.where.pop(key, None)
        if placed is not None:
            t, row, col, side = placed
            self.grey[t][row : row + side, col : col + side] = self.fill
            self.dirty.add(t)

    def changed(self) -> list[tuple[tuple[int, int], NDArray[np.uint8]]]:
        """The dirty tiles whose grey levels differ from when they were last taken; clears."""
        out = []
        for t in sorted(self.dirty):  # one iteration per tile the step wrote to
            image = self.grey[t]
            last = self.logged.get(t)
            if last is None or not np.array_equal(last, image):
                self.logged[t] = image.copy()
                out.append((t, image))
        self.dirty.clear()
        return out


@dataclass
class Regions:
    """A 3D map's boxes (or points) per leaf, grouped in regions of ``region`` voxels per edge.

    A leaf's value is ``(centres, half sizes, extra)``; ``extra`` is what the colours
    come from (compared with ``compare_extra``).
    """

    region: int
    compare_extra: bool
    boxes: dict[tuple[int, int, int], dict[int, tuple[FloatArray, FloatArray, FloatArray]]] = field(
        default_factory=dict
    )
    where: dict[int, tuple[int, int, int]] = field(default_factory=dict)
    dirty: set[tuple[int, int, int]] = field(default_factory=set)
    logged: dict[tuple[int, int, int], bytes] = field(default_factory=dict)

    def put(
        self, key: int, cell: NDArray[np.int64], value: tuple[FloatArray, FloatArray, FloatArray]
    ) -> None:
        """One leaf's ``(centres, half sizes, extra)``; empty arrays remove its boxes."""
        r = (
            int(cell[0] // self.region),
            int(cell[1] // self.region),
            int(cell[2] // self.region),
        )
        leaves = self.boxes.setdefault(r, {})
        if value[0].shape[0]:
            leaves[key] = value
        else:
            leaves.pop(key, None)
        self.where[key] = r
        self.dirty.add(r)

    def remove(self, key: int) -> None:
        """A leaf left the map."""
        r = self.where.pop(key, None)
        if r is not None:
            self.boxes[r].pop(key, None)
            self.dirty.add(r)

    def changed(self) -> list[tuple[tuple[int, int, int], FloatArray, FloatArray, FloatArray]]:
        """Each dirty region's boxes, concatenated, unless the same as when last taken; clears.

        Boxes are compared by geometry (centres and half sizes), and by ``extra`` too when
        ``compare_extra``: a refit that moves no voxel across P = 0.5 re-logs nothing.
        """
        out = []
        for r in sorted(self.dirty):  # one iteration per region the step wrote to
            leaves = self.boxes.get(r, {})
            parts = [leaves[k] for k in sorted(leaves)]
            if parts:
                centres, half, extra = (np.concatenate(p) for p in zip(*parts, strict=True))
            else:
                centres = half = np.zeros((0, 3))
                extra = np.zeros(0)
            digest = hashlib.blake2b(centres.tobytes() + half.tobytes())
            if self.compare_extra:
                digest.update(extra.tobytes())
            if self.logged.get(r) != digest.digest():
                self.logged[r] = digest.digest()
                out.append((r, centres, half, extra))
        self.dirty.clear()
        return out
