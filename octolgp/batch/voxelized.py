"""Another batch method stored as a leaf map: its values at every leaf's voxel centres."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from octolgp.batch.build import build_map
from octolgp.config import MapConfig
from octolgp.engines import LeafFit
from octolgp.errors import OctolgpError
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping.online import OnlineMap
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan
from octolgp.training import check_scans


def build_voxelized(
    scans: Iterable[Scan],
    config: MapConfig,
    method: str,
    *,
    path: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    scheduler: Any = None,
    n_jobs: int = 1,
) -> OnlineMap:
    """A map file of another batch method: its values at the voxel centres of every leaf.

    ``build_map(scans, config, method)`` (``"lgp"``, ``"gp"``, ``"mgp"`` or ``"ogm"``;
    ``scheduler`` and ``n_jobs`` as there) is built in
    memory, then evaluated at the voxel centres of every leaf the scans bring evidence to
    (the leaves of :func:`build_tiled`); the map file stores those values, so ``query``,
    ``export`` and ``OnlineMap.open`` read it like any map. GP methods store their latent
    mean and variance (and PLSC's P); the grid stores its P (mean 0 and variance 1 as
    placeholders, no hyperparameters, so queries read voxel values, not interpolations).
    Scans inserted later refit the leaves they touch with the local GPs.

    Raises
    ------
    OctolgpError
        On an unknown method (use :func:`build_tiled` for ``"leaf"``) or bad input.
    """
    if method not in ("lgp", "gp", "mgp", "ogm"):
        raise OctolgpError(f"method must be one of lgp, gp, mgp, ogm here, got {method!r}")
    scan_list = check_scans(scans, config.dim)
    gmap = build_map(scan_list, config, method=method, scheduler=scheduler, n_jobs=n_jobs)
    hp = getattr(gmap, "hyperparameters", None)
    m = OnlineMap(dataclasses.replace(config, hyperparameters=hp), path)

    def values(keys: list[int], leaves: list[Leaf]) -> Iterator[tuple[list[int], list[LeafFit]]]:
        for lo in range(0, len(keys), 512):  # batches of leaves
            out = []
            for leaf in leaves[lo : lo + 512]:  # one iteration per leaf
                centres = m.grid.voxel_centres(leaf.index)
                if hp is None:
                    prob = np.asarray(gmap.occupancy(centres), dtype=np.float64)
                    mean, var = np.zeros_like(prob), np.ones_like(prob)
                else:
                    mean, var = gmap.latent(centres)
                    prob = latent_occupancy(mean, var, hp)
                valued = dataclasses.replace(
                    leaf,
                    mean=mean.astype(np.float32),
                    var=var.astype(np.float32),
                    prob=prob.astype(np.float32),
                    refits=1,
                    fitted=False,  # another method's values: the map file keeps them
                )
                out.append(LeafFit(valued, 0))
            yield keys[lo : lo + 512], out

    try:
        m.insert_batch(scan_list, fitter=values, progress=progress)
    except BaseException:
        m.close()
        raise
    return m
