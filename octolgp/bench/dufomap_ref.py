"""DUFOMap (through the optional ``dufomap`` package) as a reference for ray-integration cost.

``pip install 'octolgp[peers]'`` installs ``dufomap`` (BSD licence, per its package
metadata; built on UFOMap, BSD-3-Clause). DUFOMap integrates each scan's rays into a
UFOMap octree and marks the space it saw fully free; its purpose is removing dynamic
points, so it is a physical reference for what integrating one scan costs, not an
occupancy map to score: this module offers no queries.

Binding calls used (``dufomap`` 1.1)
------------------------------------
- ``dufomap(resolution, d_s, d_p, num_threads)``: ``d_s`` inflates hits, ``d_p``
  inflates unknown space (metres and voxels, as in the DUFOMap paper).
- ``dufomap.run(points (n, 3) float32, pose (4, 4), cloud_transform=False)``: the
  points are already in the world frame; the pose's translation is the sensor
  origin every ray starts from (checked: a point half-way along an integrated ray
  is then classified as seen free, and is not when the origin is moved).

Every point is a return to DUFOMap: the binding has no maximum range, so a no-return
beam (ending at the scan's ``max_range``) is integrated as a ray to a hit there. That is
the same ray work OctoMap does for it (a free ray to ``max_range``), plus one hit voxel.
"""

from __future__ import annotations

import functools
import importlib
import math
import os
import time
from types import ModuleType

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.scan import Scan


@functools.cache
def _dufomap() -> ModuleType | None:
    """Import ``dufomap`` once; ``None`` when it is not installed or fails to load.

    Its native library logs with glog at INFO level on every construction; unless the
    caller set ``GLOG_minloglevel``, that is raised to warnings before the import.
    """
    os.environ.setdefault("GLOG_minloglevel", "1")
    try:
        return importlib.import_module("dufomap")
    except ImportError:
        return None


def dufomap_available() -> bool:
    """Return whether the ``dufomap`` package can be imported."""
    return _dufomap() is not None


class DufomapReference:
    """A DUFOMap map fed with octolgp's 3D scans: the ray-integration cost reference.

    Parameters
    ----------
    resolution : float
        Voxel edge, metres.
    d_s : float
        Hit inflation distance, metres (DUFOMap's ``d_s``).
    d_p : int
        Unknown inflation, voxels (DUFOMap's ``d_p``).
    num_threads : int
        DUFOMap's threads; 1 (the default) is single-threaded, like OctoMap.

    Raises
    ------
    OctolgpError
        If ``dufomap`` is not installed, or on a bad argument.
    """

    def __init__(
        self, resolution: float, d_s: float = 0.2, d_p: int = 1, num_threads: int = 1
    ) -> None:
        module = _dufomap()
        if module is None:
            raise OctolgpError(
                "DufomapReference needs the dufomap package: pip install 'octolgp[peers]'"
            )
        for name, value in (("resolution", resolution), ("d_s", d_s)):
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float | np.integer | np.floating)
                or not math.isfinite(value)
                or value <= 0
            ):
                raise OctolgpError(
                    f"DufomapReference: {name} must be a finite number > 0, got {value!r}"
                )
        for name, count in (("d_p", d_p), ("num_threads", num_threads)):
            if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 0:
                raise OctolgpError(
                    f"DufomapReference: {name} must be an integer >= 0, got {count!r}"
                )
        self.resolution = float(resolution)
        self.map = module.dufomap(
            self.resolution, float(d_s), int(d_p), num_threads=int(num_threads)
        )

    def insert_scan(self, scan: Scan) -> float:
        """Integrate one scan: every endpoint a ray from ``scan.origin`` in the world frame.

        Parameters
        ----------
        scan : Scan
            A 3D scan, world frame, metres.

        Returns
        -------
        float
            Wall-clock seconds of DUFOMap's ``run`` alone (the float32 copy and the
            pose matrix are made before the clock starts).

        Raises
        ------
        OctolgpError
            If the scan is not 3D.
        """
        if scan.dim != 3:
            raise OctolgpError(f"DufomapReference: a {scan.dim}D scan; DUFOMap maps 3D scans")
        points = np.ascontiguousarray(scan.points, dtype=np.float32)
        pose = np.eye(4)
        pose[:3, 3] = scan.origin
        start = time.perf_counter()
        self.map.run(points, pose, cloud_transform=False)
        return time.perf_counter() - start
