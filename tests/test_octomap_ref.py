"""The real OctoMap as a reference peer: hit, miss and unknown voxels; agreement with OGM."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from octolgp.batch.ogm import build_ogm
from octolgp.bench import octomap_ref
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.scan import Scan

RES = 0.1


@pytest.fixture
def pyoctomap() -> Any:
    return pytest.importorskip("pyoctomap", exc_type=ImportError)


def _ring_scan(rng: np.random.Generator, dim: int, n: int, max_range: float) -> Scan:
    origin = rng.uniform(-1.0, 1.0, size=dim)
    direction = rng.normal(size=(n, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return Scan(origin, origin + rng.uniform(0.3, 4.0, size=(n, 1)) * direction, max_range)


def test_missing_binding_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(octomap_ref, "_pyoctomap", lambda: None)
    assert not octomap_ref.octomap_available()
    with pytest.raises(OctolgpError, match="pyoctomap"):
        OctomapReference(RES, 3)


@pytest.mark.usefixtures("pyoctomap")
def test_available() -> None:
    assert octomap_available()


@pytest.mark.usefixtures("pyoctomap")
@pytest.mark.parametrize("dim", [2, 3])
def test_hit_free_unknown(dim: int) -> None:
    # One beam along +x from the origin's voxel centre to the voxel centred at 2.05 m.
    origin = np.full(dim, 0.05)
    end = origin.copy()
    end[0] = 2.05
    ref = OctomapReference(RES, dim)
    seconds = ref.insert_scan(Scan(origin, end[None, :]))
    assert seconds >= 0.0
    along = origin + np.outer([0.0, 0.5, 1.0, 1.9], np.eye(dim)[0])
    far = origin + np.outer([5.0, -3.0], np.ones(dim))
    p_hit, *p_free = ref.occupancy(np.vstack([end, along]))
    # OctoMap's default sensor model: one hit 0.7, one miss 0.4.
    assert p_hit == pytest.approx(0.7, abs=1e-6)
    np.testing.assert_allclose(p_free, 0.4, atol=1e-6)
    np.testing.assert_array_equal(ref.occupancy(far), 0.5)
    # Just past the hit is unknown: the ray stops at its end voxel.
    np.testing.assert_array_equal(ref.occupancy((end + np.eye(dim)[0] * RES)[None, :]), 0.5)


@pytest.mark.usefixtures("pyoctomap")
def test_repeated_hits_clamp() -> None:
    ref = OctomapReference(RES, 3)
    scan = Scan(np.full(3, 0.05), np.array([[1.05, 0.05, 0.05]]))
    for _ in range(20):
        ref.insert_scan(scan)
    p_hit, p_free = ref.occupancy([[1.05, 0.05, 0.05], [0.55, 0.05, 0.05]])
    assert p_hit == pytest.approx(0.971, abs=1e-3)
    assert p_free == pytest.approx(0.1192, abs=1e-3)


@pytest.mark.usefixtures("pyoctomap")
def test_no_return_clears_to_max_range_without_hit() -> None:
    origin = np.full(3, 0.05)
    ends = origin + np.array([[3.0, 0.0, 0.0], [0.0, 10.0, 0.0]])  # exactly and past max_range
    ref = OctomapReference(RES, 3)
    ref.insert_scan(Scan(origin, ends, max_range=3.0))
    probe = origin + np.array(
        [[2.5, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 2.5, 0.0], [0.0, 3.5, 0.0], [0.0, 10.0, 0.0]]
    )
    p = ref.occupancy(probe)
    np.testing.assert_allclose(p[[0, 2]], 0.4, atol=1e-6)
    assert np.all(p <= 0.5)  # no hit anywhere: the end voxel is free or unknown
    np.testing.assert_array_equal(p[3:], 0.5)


@pytest.mark.usefixtures("pyoctomap")
def test_zero_length_beam_is_ignored() -> None:
    origin = np.full(2, 0.05)
    ref = OctomapReference(RES, 2)
    ref.insert_scan(Scan(origin, origin[None, :]))
    np.testing.assert_array_equal(ref.occupancy(origin[None, :]), 0.5)


@pytest.mark.parametrize("dim", [2, 3])
def test_occupancy_matches_per_point_search(pyoctomap: Any, dim: int) -> None:
    rng = np.random.default_rng(dim)
    ref = OctomapReference(RES, dim)
    ref.insert_scan(_ring_scan(rng, dim, 300, max_range=3.0))
    query = np.vstack([rng.uniform(-4.0, 4.0, size=(3000, dim)), np.full((2, dim), 1e4)])
    expected = []
    for q in ref._lift(query).tolist():
        node = ref.tree.search(q) if abs(q[0]) < 1e3 else None  # far points: out of the tree
        expected.append(0.5 if node is None else node.getOccupancy())
    np.testing.assert_array_equal(ref.occupancy(query), expected)


@pytest.mark.usefixtures("pyoctomap")
@pytest.mark.parametrize("dim", [2, 3])
def test_agrees_with_octolgp_ogm(dim: int) -> None:
    # octolgp's OGM implements OctoMap's insertPointCloud; the real one must agree.
    rng = np.random.default_rng(10 + dim)
    scans = [_ring_scan(rng, dim, 200, max_range=3.0) for _ in range(4)]
    ref = OctomapReference(RES, dim)
    for scan in scans:
        ref.insert_scan(scan)
    grid = build_ogm(scans, MapConfig(dim=dim, resolution=RES))
    centres = grid.voxel_centres()
    np.testing.assert_allclose(ref.occupancy(centres), grid.occupancy(centres), atol=1e-6)
    query = rng.uniform(-5.0, 5.0, size=(5000, dim))
    np.testing.assert_allclose(ref.occupancy(query), grid.occupancy(query), atol=1e-6)


@pytest.mark.usefixtures("pyoctomap")
def test_rejects_bad_input() -> None:
    with pytest.raises(OctolgpError):
        OctomapReference(0.0, 3)
    with pytest.raises(OctolgpError):
        OctomapReference(RES, 4)
    ref = OctomapReference(RES, 3)
    with pytest.raises(OctolgpError):
        ref.insert_scan(Scan(np.zeros(2), np.ones((1, 2))))
    with pytest.raises(OctolgpError):
        ref.occupancy(np.zeros((2, 2)))
    with pytest.raises(OctolgpError, match="outside"):
        ref.insert_scan(Scan(np.zeros(3), np.array([[4000.0, 0.0, 0.0]])))
