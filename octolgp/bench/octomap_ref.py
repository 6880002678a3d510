"""The real OctoMap (through the optional ``pyoctomap`` binding) as a reference peer.

``pip install octolgp[octomap]`` installs ``pyoctomap``; everything here raises a
clear :class:`~octolgp.errors.OctolgpError` when it is missing, and
:func:`octomap_available` lets callers and tests skip instead.

Binding calls used (``pyoctomap`` 1.2)
--------------------------------------
- ``OcTree(resolution)``: OctoMap's default sensor model (hit 0.7, miss 0.4,
  clamping 0.1192–0.971).
- ``OcTree.insertPointCloud(points (n, 3) float64, origin (3,) float64, max_range)``:
  OctoMap's native ``insertPointCloud`` (``computeUpdate`` ray casting, then one
  update per free and per occupied voxel, occupied winning within a scan), followed
  by ``updateInnerOccupancy``.
- ``OcTree.search(OcTreeKey)`` and ``OcTreeNode.getOccupancy()`` per voxel. The
  binding has no batched search (its ``getLabels`` is itself a per-point Python
  loop and returns only labels), so :meth:`OctomapReference.occupancy` computes
  the keys with numpy, exactly as OctoMap's ``search(double x, double y, double z)``
  does, and loops in Python over the *distinct* voxels only (about 1 µs each).
"""

from __future__ import annotations

import functools
import importlib
import math
import time
from types import ModuleType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import NO_RETURN_RTOL, Scan, as_points

FloatArray = NDArray[np.float64]

TREE_MAX_VAL = 1 << 15
"""OctoMap's ``tree_max_val``: the key of coordinate 0 on each axis (depth 16)."""


MIN_BEAM_LENGTH = 1e-9
"""Beams this short (metres) carry no direction and are not inserted, as in training."""

_MAX_RANGE_SLACK = 1e-6
"""Relative slack on the ``max_range`` handed to OctoMap, above float32 rounding (~6e-8)."""


@functools.cache
def _pyoctomap() -> ModuleType | None:
    """Import ``pyoctomap`` once; ``None`` when it is not installed or fails to load."""
    try:
        return importlib.import_module("pyoctomap")
    except ImportError:
        return None


def octomap_available() -> bool:
    """Return whether the ``pyoctomap`` binding can be imported."""
    return _pyoctomap() is not None


class OctomapReference:
    """An OctoMap ``OcTree`` fed with octolgp scans: the reference log-odds peer.

    2D scans are mapped in the voxel layer ``0 <= z < resolution``: points and origin
    get ``z = resolution / 2``, and so do 2D queries. Zero-length beams are dropped.
    No-return beams (``length >= max_range * (1 - 1e-9)``) clear free space to
    ``max_range`` and add no hit, as octolgp's training data does.

    Parameters
    ----------
    resolution : float
        Voxel edge, metres. The tree (depth 16) addresses ``[-32768, 32768) *
        resolution`` on each axis; points outside read as unknown (0.5).
    dim : int
        2 or 3; scans and queries must match it.

    Raises
    ------
    OctolgpError
        If ``pyoctomap`` is not installed, or on a bad ``resolution`` or ``dim``.

    Notes
    -----
    OctoMap stores coordinates as float32: inserted endpoints are rounded to float32
    before their voxel is found, while queries use float64 keys (as OctoMap's
    ``search(double, double, double)`` does). The two differ only for points within
    about 1e-7 relative of a voxel face.
    """

    def __init__(self, resolution: float, dim: int) -> None:
        module = _pyoctomap()
        if module is None:
            raise OctolgpError(
                "OctomapReference needs the pyoctomap package: pip install 'octolgp[octomap]'"
            )
        if (
            isinstance(resolution, bool)
            or not isinstance(resolution, int | float | np.integer | np.floating)
            or not math.isfinite(resolution)
            or resolution <= 0
        ):
            raise OctolgpError(
                f"OctomapReference: resolution must be a finite number > 0, got {resolution!r}"
            )
        if isinstance(dim, bool) or dim not in (2, 3):
            raise OctolgpError(f"OctomapReference: dim must be 2 or 3, got {dim!r}")
        self.resolution = float(resolution)
        self.dim = int(dim)
        self._module = module
        self.tree = module.OcTree(self.resolution)

    def _lift(self, points: FloatArray) -> FloatArray:
        """Return ``(n, 3)`` float64 points: 2D ones get ``z = resolution / 2``."""
        if self.dim == 3:
            return np.ascontiguousarray(points, dtype=np.float64)
        z = np.full((points.shape[0], 1), 0.5 * self.resolution)
        return np.ascontiguousarray(np.hstack([points, z]), dtype=np.float64)

    def _inside(self, points: FloatArray) -> NDArray[np.bool_]:
        """Per point of shape ``(n, dim)`` or ``(n, 3)``: whether every axis has a key."""
        scaled = np.floor(points * (1.0 / self.resolution))
        return np.asarray(((scaled >= -TREE_MAX_VAL) & (scaled < TREE_MAX_VAL)).all(axis=1))

    def insert_scan(self, scan: Scan) -> float:
        """Ray-cast one scan into the tree with OctoMap's ``insertPointCloud``.

        Parameters
        ----------
        scan : Scan
            Origin and endpoints in the world frame, metres, of dimension ``dim``.

        Returns
        -------
        float
            Wall-clock seconds of the insertion, including the conversion to the
            binding's arrays.

        Raises
        ------
        OctolgpError
            If the scan's dimension is not ``dim``, or its origin or a real return
            lies outside the tree (OctoMap would only print an error and skip it).
        """
        if scan.dim != self.dim:
            raise OctolgpError(f"OctomapReference: a {scan.dim}D scan in a {self.dim}D map")
        if not self._inside(np.vstack([scan.points, scan.origin])).all():
            half = TREE_MAX_VAL * self.resolution
            raise OctolgpError(
                f"OctomapReference: Scan.points or Scan.origin outside [{-half:g}, {half:g}) m"
            )
        start = time.perf_counter()
        delta = scan.points - scan.origin
        length = np.linalg.norm(delta, axis=1)
        keep = length > MIN_BEAM_LENGTH
        points = scan.points[keep]
        max_range = -1.0  # OctoMap: unlimited
        if scan.max_range is not None:
            # A no-return is moved to twice max_range along its beam, and OctoMap is told
            # max_range (plus slack for its float32 norms): it clears the ray to max_range
            # and adds no hit, while every real return stays below the limit.
            no_return = length[keep] >= scan.max_range * (1.0 - NO_RETURN_RTOL)
            scale = np.where(no_return, 2.0 * scan.max_range / length[keep], 1.0)
            points = scan.origin + scale[:, None] * delta[keep]
            max_range = scan.max_range * (1.0 + _MAX_RANGE_SLACK)
        if points.shape[0]:
            self.tree.insertPointCloud(
                self._lift(points), self._lift(scan.origin[None, :])[0], max_range=max_range
            )
        return time.perf_counter() - start

    def occupancy(self, points: ArrayLike) -> FloatArray:
        """OctoMap's occupancy probability of the voxel holding each query point.

        Parameters
        ----------
        points : array_like of shape (q, dim)
            Query points in the world frame, metres.

        Returns
        -------
        ndarray of shape (q,)
            The node's ``getOccupancy()`` (a pruned parent's when the voxel was
            pruned), exactly 0.5 where the voxel is unknown or outside the tree.

        Raises
        ------
        OctolgpError
            On a wrong shape or non-finite values.
        """
        X = self._lift(as_points(points, "OctomapReference.occupancy: points", dim=self.dim))
        # OctoMap coordToKeyChecked(double): floor(resolution_factor * x) + tree_max_val.
        scaled = np.floor(X * (1.0 / self.resolution))
        inside = self._inside(X)
        probs = np.full(X.shape[0], 0.5)
        if not inside.any():
            return probs
        keys = scaled[inside].astype(np.int64) + TREE_MAX_VAL
        # Distinct voxels, via keys packed into one int64 (x | y << 16 | z << 32).
        packed = keys[:, 0] | (keys[:, 1] << 16) | (keys[:, 2] << 32)
        voxels, inverse = np.unique(packed, return_inverse=True)
        # The binding searches one key per call: loop over distinct voxels only.
        key_type = self._module.OcTreeKey
        search = self.tree.search
        voxel_probs = np.full(voxels.shape[0], 0.5)
        for i, v in enumerate(voxels.tolist()):
            node = search(key_type(v & 0xFFFF, (v >> 16) & 0xFFFF, v >> 32))
            if node is not None:
                voxel_probs[i] = node.getOccupancy()
        probs[inside] = voxel_probs[inverse]
        return probs
