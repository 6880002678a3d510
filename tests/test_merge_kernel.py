"""The compiled merge of two ascending key arrays against the numpy sort and search."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octolgp.geometry import merge_kernel
from octolgp.observations import merge_unique

pytestmark = pytest.mark.skipif(not merge_kernel.AVAILABLE, reason="numba is not installed")

keys = st.lists(st.integers(0, 60), max_size=40).map(lambda v: np.unique(np.array(v, np.int64)))


@settings(max_examples=200, deadline=None)
@given(a=keys, b=keys)
def test_merge_positions_equal_the_sorted_union_and_its_search(
    a: np.ndarray, b: np.ndarray
) -> None:
    union, at_a, at_b = merge_kernel.merge_positions(a, b)
    want = merge_unique(a, b)
    np.testing.assert_array_equal(union, want)
    np.testing.assert_array_equal(at_a, np.searchsorted(want, a))
    np.testing.assert_array_equal(at_b, np.searchsorted(want, b))
    assert union.dtype == at_a.dtype == at_b.dtype == np.int64


def test_merge_positions_of_large_key_runs() -> None:
    rng = np.random.default_rng(0)
    a = np.unique(rng.integers(0, 1 << 48, 5000))
    b = np.unique(np.r_[rng.integers(0, 1 << 48, 20000), a[::3]])
    union, at_a, at_b = merge_kernel.merge_positions(a, b)
    np.testing.assert_array_equal(union, merge_unique(a, b))
    np.testing.assert_array_equal(union[at_a], a)
    np.testing.assert_array_equal(union[at_b], b)
