"""The field of view between beams: voxels a 2D scan swept without a beam through them.

The lattice engine's honest-unknown rule (``LatticeConfig.fill_voxels``) lets a voxel
take the GP's value only near a voxel that was observed. Diverging beams leave gaps
that no beam crosses, although the sensor looked across them: this module gives, per
step, the voxels those gaps hold, which count as observed for that rule but are no
evidence for the GP.

**The rule.** Sort a scan's beams by direction. Two beams adjacent in that order (the
last and the first too, around the circle) whose directions are more than 0 and at most
``LatticeConfig.sweep_angle`` degrees apart *sweep* the sector between them: the points
whose direction lies between theirs and whose distance from the sensor is at most the
nearer of the two beams' free-segment ends (the return less ``free_margin``, the
no-return range, or ``free_range``: :func:`octolgp.training.split_beams`). A voxel is
swept when its centre lies in such a sector (:func:`in_sector`, with its
comparisons inclusive). A voxel is *known* when a voxel within ``fill_voxels`` of it was
observed or swept; elsewhere it reads 0.5.

**What is kept.** A voxel centre in a sector at a distance ``ρ`` from the sensor lies
within ``ρ sin(Δθ / 2)`` of the nearer beam's free segment, whose voxels are observed,
so where ``ρ sin(Δθ / 2) < (fill_voxels + 1/2) × resolution`` the voxel is known whatever
it is swept. :func:`swept_keys` gives the swept voxels beyond that distance only: the
known voxels are exactly those of the whole rule, and the sectors near the sensor,
where beams are dense, cost nothing (a 1° scanner with the 2D defaults sweeps voxels
only beyond 28.6 m).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from octolgp.config import MapConfig
from octolgp.geometry.keys import KeyRegion, pack_keys
from octolgp.scan import Scan
from octolgp.training import IntArray, free_lengths, stack_beams

SAMPLES_PER_BLOCK = 1 << 20
"""Polar samples of the sectors handled at once (bounds the transient arrays)."""

_SAFETY = 1.0 - 1e-6
"""The near distance is taken this much shorter (rounding never drops a voxel)."""

FloatArray = NDArray[np.float64]


def beam_sectors(
    scans: list[Scan], config: MapConfig
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The sectors swept between the beams of 2D scans (see the module's rule).

    Parameters
    ----------
    scans : list of Scan
        2D scans, world frame.
    config : MapConfig
        Uses ``sweep_angle`` and the sensor model (``free_margin``, ``free_range``,
        ``no_return_range``).

    Returns
    -------
    origin : ndarray of shape (s, 2)
        Each sector's sensor position, metres.
    start : ndarray of shape (s,)
        The direction of its first beam, radians in ``[-π, π]``.
    width : ndarray of shape (s,)
        The angle to the second beam, radians in ``(0, sweep_angle]``.
    reach : ndarray of shape (s,)
        The nearer free-segment end of the two beams, metres (``> 0``).
    """
    none = np.zeros(0)
    if config.sweep_angle <= 0 or not scans:
        return np.zeros((0, 2)), none, none, none
    origins, ends, max_range = stack_beams(scans)
    vec = ends - origins
    length = np.hypot(vec[:, 0], vec[:, 1])
    valid, _, _, free_len = free_lengths(
        length, max_range, config.free_margin, config.free_range, config.no_return_range
    )
    scan = np.repeat(np.arange(len(scans), dtype=np.int64), [len(s) for s in scans])
    reach = np.maximum(free_len[valid], 0.0)
    vec, scan, origins = vec[valid], scan[valid], origins[valid]
    angle = np.arctan2(vec[:, 1], vec[:, 0])
    order = np.lexsort((reach, angle, scan))
    scan, angle, reach, origins = scan[order], angle[order], reach[order], origins[order]
    # each beam with the next one of its scan; a scan's last beam with its first
    first = np.searchsorted(scan, scan, side="left")
    last = np.searchsorted(scan, scan, side="right") - 1
    idx = np.arange(scan.size)
    nxt = np.where(idx == last, first, idx + 1)
    width = np.where(idx == last, angle[nxt] + 2.0 * math.pi - angle, angle[nxt] - angle)
    near = np.minimum(reach, reach[nxt])
    keep = (nxt != idx) & (width > 0) & (width <= math.radians(config.sweep_angle)) & (near > 0)
    return origins[keep], angle[keep], width[keep], near[keep]


def in_sector(
    centres: FloatArray, origin: FloatArray, start: FloatArray, width: FloatArray, reach: FloatArray
) -> NDArray[np.bool_]:
    """Whether each point lies in its sector (the rule's test; comparisons inclusive).

    Parameters
    ----------
    centres : ndarray of shape (n, 2)
        Points, metres.
    origin : ndarray of shape (n, 2)
    start, width, reach : ndarray of shape (n,)
        Each point's sector, as :func:`beam_sectors` gives them.
    """
    offset = centres - origin
    rho = np.hypot(offset[:, 0], offset[:, 1])
    turn = np.mod(np.arctan2(offset[:, 1], offset[:, 0]) - start, 2.0 * math.pi)
    out: NDArray[np.bool_] = (turn <= width) & (rho <= reach)
    return out


def swept_keys(scans: list[Scan], config: MapConfig, region: KeyRegion | None = None) -> IntArray:
    """Packed keys of the voxels the scans swept that may be unknown otherwise, ascending.

    The voxels whose centres lie in a sector (:func:`beam_sectors`) farther from the
    sensor than ``(fill_voxels + 1/2) × resolution / sin(width / 2)`` (the module's
    docstring says why the nearer ones are known anyway). None where the rule is off
    (``sweep_angle`` 0), where every voxel of a leaf is filled (``fill_voxels`` -1) and
    in 3D.

    Parameters
    ----------
    scans : list of Scan
        World-frame scans of dimension ``config.dim`` (points addressable).
    config : MapConfig
    region : KeyRegion, optional
        Only the voxels in it.

    Returns
    -------
    ndarray of int64, shape (m,)
    """
    empty = np.zeros(0, dtype=np.int64)
    if config.dim != 2 or config.fill_voxels < 0 or config.sweep_angle <= 0:
        return empty
    res = config.resolution
    origin, start, width, reach = beam_sectors(scans, config)
    near = (config.fill_voxels + 0.5) * res * _SAFETY / np.sin(width / 2.0)
    far = reach >= near
    origin, start, width, reach, near = (a[far] for a in (origin, start, width, reach, near))
    if not reach.size:
        return empty
    # polar samples at most half a voxel apart along both directions: every point of a
    # sector's far part lies within 0.36 voxel of one, so in a sample's voxel
    step = 0.5 * res
    rings = np.ceil((reach - near) / step).astype(np.int64) + 1
    spokes = np.ceil(reach * width / step).astype(np.int64) + 1
    per = rings * spokes
    bounds = np.searchsorted(np.cumsum(per), np.arange(0, per.sum(), SAMPLES_PER_BLOCK), "right")
    bounds = np.unique(np.r_[0, bounds, per.size])
    half = 1 << (config.tree_depth - 1)
    parts = [empty]
    for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):  # per block
        n = per[lo:hi]
        sector = np.repeat(np.arange(lo, hi), n)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        ring, spoke = k // spokes[sector], k % spokes[sector]
        rho = np.minimum(near[sector] + ring * step, reach[sector])
        phi = start[sector] + width[sector] * spoke / np.maximum(spokes[sector] - 1, 1)
        samples = origin[sector] + rho[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        keys = np.floor(samples / res).astype(np.int64)
        code = pack_keys(keys + half) | (sector.astype(np.int64) << 32)
        code = np.unique(code)  # one candidate per (sector, voxel)
        sector = code >> 32
        keys = np.stack([code & 0xFFFF, (code >> 16) & 0xFFFF], axis=1) - half
        inside = in_sector(
            (keys + 0.5) * res, origin[sector], start[sector], width[sector], reach[sector]
        )
        parts.append(np.unique(code[inside] & 0xFFFFFFFF))
    out = np.unique(np.concatenate(parts))
    if region is not None:
        out = out[region.contains(out)]
    return out
