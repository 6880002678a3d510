"""OctoMap keys: round trips, range limits, packing and child order."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import (
    addressable_mask,
    addressable_range,
    child_index,
    coord_to_key,
    key_to_coord,
    pack_keys,
    unpack_keys,
)

resolutions = st.sampled_from([0.05, 0.1, 0.2, 0.25, 1.0])
coords = st.floats(-500.0, 500.0, allow_nan=False, allow_infinity=False)
key_values = st.integers(0, 2**16 - 1)


def test_known_keys() -> None:
    keys = coord_to_key([[0.05, -0.05, 0.0], [-3276.8, 3276.75, 0.1]], 0.1)
    assert keys.dtype == np.int64
    np.testing.assert_array_equal(keys, [[32768, 32767, 32768], [0, 65535, 32769]])
    np.testing.assert_allclose(key_to_coord(keys[:1], 0.1), [[0.05, -0.05, 0.05]])


@given(st.lists(st.tuples(coords, coords, coords), min_size=1, max_size=20), resolutions)
def test_coord_key_round_trip(points: list[tuple[float, float, float]], res: float) -> None:
    pts = np.array(points)
    keys = coord_to_key(pts, res)
    centres = key_to_coord(keys, res)
    # The centre lies in the same voxel, within half a voxel of the point.
    assert np.all(np.abs(centres - pts) <= 0.5 * res * (1 + 1e-9))
    np.testing.assert_array_equal(coord_to_key(centres, res), keys)


@given(st.lists(st.tuples(key_values, key_values), min_size=1, max_size=20), resolutions)
def test_key_coord_round_trip_2d(keys: list[tuple[int, int]], res: float) -> None:
    k = np.array(keys, dtype=np.int64)
    np.testing.assert_array_equal(coord_to_key(key_to_coord(k, res), res), k)


def test_addressable_range() -> None:
    assert addressable_range(0.1) == pytest.approx((-3276.8, 3276.8))
    assert addressable_range(1.0, tree_depth=4) == (-8.0, 8.0)


def test_range_edges_small_tree() -> None:
    keys = coord_to_key([[-8.0], [7.99]], 1.0, tree_depth=4)
    np.testing.assert_array_equal(keys, [[0], [15]])
    with pytest.raises(OctolgpError, match=r"points.*\[-8, 8\) m"):
        coord_to_key([[8.0]], 1.0, tree_depth=4)
    np.testing.assert_array_equal(
        addressable_mask([[-8.0], [7.5], [8.0], [-8.01]], 1.0, tree_depth=4),
        [True, True, False, False],
    )


def test_out_of_range_names_points_and_range() -> None:
    with pytest.raises(OctolgpError, match=r"points row 1 .*\[-3276.8, 3276.8\) m"):
        coord_to_key([[0.0, 0.0], [3300.0, 0.0]], 0.1)
    with pytest.raises(OctolgpError, match="points"):
        coord_to_key([[0.0, 1e300]], 0.1)


@pytest.mark.parametrize(
    ("points", "kwargs"),
    [
        ([[np.nan, 0.0]], {}),
        ([0.0, 1.0], {}),
        ([[0.0, 1.0]], {"resolution": 0.0}),
        ([[0.0, 1.0]], {"tree_depth": 17}),
        ([[0.0, 1.0]], {"tree_depth": 0}),
    ],
)
def test_bad_coord_input(points: object, kwargs: dict[str, float]) -> None:
    args = {"resolution": 0.1, **kwargs}
    with pytest.raises(OctolgpError):
        coord_to_key(points, **args)  # type: ignore[arg-type]


@given(st.lists(st.tuples(key_values, key_values, key_values), min_size=1, max_size=30))
def test_pack_unpack_round_trip(keys: list[tuple[int, int, int]]) -> None:
    k = np.array(keys, dtype=np.int64)
    packed = pack_keys(k)
    assert packed.dtype == np.int64
    assert (packed >= 0).all()
    np.testing.assert_array_equal(unpack_keys(packed, 3), k)
    np.testing.assert_array_equal(unpack_keys(pack_keys(k[:, :2]), 2), k[:, :2])


@given(st.lists(st.tuples(key_values, key_values, key_values), min_size=1, max_size=30))
def test_packed_order_is_z_y_x_order(keys: list[tuple[int, int, int]]) -> None:
    k = np.unique(np.array(keys, dtype=np.int64), axis=0)
    by_packed = k[np.argsort(pack_keys(k))]
    by_zyx = k[np.lexsort((k[:, 0], k[:, 1], k[:, 2]))]
    np.testing.assert_array_equal(by_packed, by_zyx)
    # Packed keys are unique per voxel, so searchsorted finds every voxel.
    sorted_packed = np.sort(pack_keys(k))
    np.testing.assert_array_equal(
        sorted_packed[np.searchsorted(sorted_packed, pack_keys(k))], pack_keys(k)
    )


def test_pack_rejects_bad_keys() -> None:
    with pytest.raises(OctolgpError, match="keys"):
        pack_keys([[-1, 0, 0]])
    with pytest.raises(OctolgpError, match="keys"):
        pack_keys([[2**16, 0, 0]])
    with pytest.raises(OctolgpError, match="keys"):
        pack_keys([[0.5, 0.0, 0.0]])
    with pytest.raises(OctolgpError, match="dim"):
        unpack_keys(np.array([0]), 4)
    with pytest.raises(OctolgpError, match="packed"):
        unpack_keys(np.array([2**32]), 2)


def test_child_index_hand_computed() -> None:
    # OctoMap's computeChildIdx: bit `level` of x adds 1, of y adds 2, of z adds 4.
    keys = np.array([[5, 6, 3]])  # binary x=101, y=110, z=011
    assert [int(child_index(keys, level)[0]) for level in range(4)] == [5, 6, 3, 0]
    # The root (level 15 at depth 16) splits at 0 m: (+x, -y, +z) is octant 5.
    root_keys = coord_to_key([[0.05, -0.05, 0.05], [-1.0, 2.0, -3.0], [1.0, 1.0, 1.0]], 0.1)
    np.testing.assert_array_equal(child_index(root_keys, 15), [5, 2, 7])
    # 2D keys have no z bit.
    np.testing.assert_array_equal(child_index(root_keys[:, :2], 15), [1, 2, 3])


def test_child_index_rebuilds_keys() -> None:
    # The child indices along the path from the root spell the key, as in OctoMap.
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2**16, size=(50, 3))
    rebuilt = np.zeros_like(keys)
    for level in range(16):
        idx = child_index(keys, level).astype(np.int64)
        rebuilt += ((idx[:, None] >> np.arange(3)) & 1) << level
    np.testing.assert_array_equal(rebuilt, keys)


def test_child_index_rejects_bad_level() -> None:
    with pytest.raises(OctolgpError, match="level"):
        child_index([[0, 0, 0]], 16)
