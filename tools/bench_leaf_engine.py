"""Unit costs behind the choice of a faster leaf engine (issue #14), on this CPU.

The Matérn kernel per value, ``cdist`` vs ``pdist``, and the building blocks of a
leaf GP in information form on fixed inducing points: absorbing nodes into
``m``-point statistics, batched Cholesky, and predicting 512 voxels of 2,600 leaves
from one constant ``K_*u``. Best of 3 (2 for the big ones). Figures:
``docs/design-realtime-3d.md``.

Run from the repository root::

    .venv/bin/python tools/bench_leaf_engine.py
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.distance import cdist, pdist

from octolgp.gp.kernels import matern32


def best(f: Callable[[], object], n: int = 3) -> float:
    """Fastest of ``n`` runs, seconds."""
    out = np.inf
    for _ in range(n):  # a few repeats
        t0 = time.perf_counter()
        f()
        out = min(out, time.perf_counter() - t0)
    return float(out)


def lattice(k: int, edge: float) -> np.ndarray:
    """Centres of a ``k``³ lattice over a cube of side ``edge``."""
    idx = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return (idx + 0.5) * (edge / k)


def main() -> None:
    rng = np.random.default_rng(0)
    r = rng.uniform(0, 3, 4_000_000)
    print(f"matern32: {1e9 * best(lambda: matern32(r, 0.8, 2.0)) / r.size:.1f} ns per value")
    print(f"np.exp:   {1e9 * best(lambda: np.exp(-r)) / r.size:.1f} ns per value")
    X = rng.uniform(0, 2, (2000, 3))
    print(
        f"cdist 2000x2000 {1e3 * best(lambda: cdist(X, X)):.1f} ms, "
        f"pdist {1e3 * best(lambda: pdist(X)):.1f} ms"
    )
    voxels = lattice(8, 1.6)  # a 3D leaf at 0.2 m
    n_leaves = 2600
    for m in (64, 27):
        inducing = lattice(round(m ** (1 / 3)), 1.6)
        Ksu = matern32(cdist(voxels, inducing), 0.8, 2.0)  # the same for every leaf
        S = rng.standard_normal((n_leaves, m, m))
        S = S @ S.transpose(0, 2, 1) / m + np.eye(m)
        w = rng.standard_normal((n_leaves, m))

        def predict(Ksu: np.ndarray = Ksu, S: np.ndarray = S, w: np.ndarray = w) -> object:
            mean = w @ Ksu.T
            var = (np.matmul(Ksu[None], S) * Ksu[None]).sum(-1)
            return mean, var

        print(f"m={m}: predict {n_leaves} leaves x 512 voxels {1e3 * best(predict, 2):.0f} ms")
        print(f"m={m}: batched Cholesky {1e3 * best(lambda S=S: np.linalg.cholesky(S), 2):.0f} ms")
        nodes = rng.uniform(0, 1.6, (100_000, 3))

        def absorb(nodes: np.ndarray = nodes, inducing: np.ndarray = inducing) -> object:
            K = matern32(cdist(nodes, inducing), 0.8, 2.0)
            return K.T @ K

        print(f"m={m}: absorb 100k nodes {1e3 * best(absorb, 2):.0f} ms")


if __name__ == "__main__":
    main()
