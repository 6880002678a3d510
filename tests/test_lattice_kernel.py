"""The compiled lattice posterior against the stacked numpy products it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from octolgp import Hyperparameters
from octolgp.gp import lattice_kernel
from octolgp.gp.lattice import (
    COMPILED_UP_TO,
    LatticeGeometry,
    Returns,
    lattice_posterior,
    lattice_tables,
)

HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def _leaves(
    rng: np.random.Generator, g: LatticeGeometry, n: int, density: float
) -> tuple[np.ndarray, np.ndarray, Returns]:
    """Saturated counts as the engine stores them and returns inside the halo box."""
    H = g.n_halo
    hits = (rng.random((n, H)) < density / 8) * rng.integers(1, 4, (n, H))
    frees = (rng.random((n, H)) < density) * rng.integers(1, 6, (n, H))
    per_leaf = rng.integers(0, 7, n)
    per_leaf[::5] = 0  # some leaves see no return
    edge = g.box * g.resolution
    points = rng.random((int(per_leaf.sum()), g.dim)) * edge - g.halo * g.resolution
    weights = rng.integers(1, 4, points.shape[0]).astype(np.float64)
    return hits.astype(np.uint8), frees.astype(np.uint8), Returns(points, weights, per_leaf)


@pytest.mark.parametrize(
    ("dim", "side", "halo", "k"),
    [(3, 4, 1, 3), (3, 4, 1, 4), (3, 8, 2, 3), (2, 16, 4, 6), (2, 16, 4, 10), (2, 8, 2, 5)],
)
@pytest.mark.parametrize("density", [0.02, 0.3, 1.0])
@pytest.mark.parametrize("with_returns", [False, True])
def test_the_compiled_posterior_is_the_numpy_one(
    dim: int, side: int, halo: int, k: int, density: float, with_returns: bool
) -> None:
    g = LatticeGeometry(dim, side, halo, k, 0.2)
    tables = lattice_tables(g, HP)
    rng = np.random.default_rng(dim * 1000 + k * 10 + int(density * 10))
    hits, frees, returns = _leaves(rng, g, 40, density)
    hits[3] = frees[3] = 0  # nothing observed but (maybe) returns
    given = returns if with_returns else None
    ref = lattice_posterior(tables, hits, frees, 0.06, given, compiled=False)
    out = lattice_posterior(tables, hits, frees, 0.06, given, compiled=True)
    # stated tolerance: 1e-9 of the prior's scale; the same float64 system summed and
    # factored in another order (measured: about 1e-11 on the mean, 1e-13 on the variance)
    scale = HP.signal_variance
    np.testing.assert_allclose(out[0], ref[0], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(out[1], ref[1], rtol=0, atol=1e-9 * scale)


def test_no_leaves_and_unobserved_leaves() -> None:
    g = LatticeGeometry(3, 4, 1, 3, 0.2)
    tables = lattice_tables(g, HP)
    none = np.zeros((0, g.n_halo), np.uint8)
    mean, var = lattice_posterior(tables, none, none, 0.06, compiled=True)
    assert mean.shape == var.shape == (0, 64)
    empty = np.zeros((2, g.n_halo), np.uint8)
    mean, var = lattice_posterior(tables, empty, empty, 0.06, compiled=True)
    np.testing.assert_array_equal(mean, 0.0)  # the prior: A = I, b = 0
    np.testing.assert_allclose(var, HP.signal_variance, rtol=1e-9)


def test_the_default_path_is_the_compiled_kernel_on_small_lattices(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[int] = []
    real = lattice_kernel.leaf_posteriors

    def spy(*args: object, **kwargs: object) -> tuple[np.ndarray, np.ndarray]:
        calls.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(lattice_kernel, "leaf_posteriors", spy)
    rng = np.random.default_rng(0)
    for k, expect in ((3, 1), (12, 0)):  # m = 27 and 144 (2D)
        dim = 3 if k == 3 else 2
        g = LatticeGeometry(dim, 4 if dim == 3 else 16, 1 if dim == 3 else 4, k, 0.2)
        assert (g.n_inducing <= COMPILED_UP_TO) == bool(expect)
        hits, frees, _ = _leaves(rng, g, 3, 0.3)
        calls.clear()
        lattice_posterior(lattice_tables(g, HP), hits, frees, 0.06)
        assert len(calls) == expect
