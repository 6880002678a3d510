r"""The lattice leaf GP: voxel observations, a fixed inducing lattice, batched over leaves.

The numerics of the online map's default leaf engine (:mod:`octolgp.engines.lattice`;
the design and the measurements behind it are in ``docs/design-realtime-3d.md``).

**Model.** A leaf's training data are its halo box's observations: returns, each a
point observation (target +1) of the latent ``f`` at its measured position with weight
``w_r`` (its voxel's return count), and free voxels, each an observation (target −1) at
the voxel centre with weight ``γ f_v`` (``f_v`` the voxel's effective free count,
``γ`` the free weight), every observation with noise ``σn² / w``. Which voxels count,
and how often, is the engine's rule (:mod:`octolgp.engines.lattice`,
:func:`octolgp.observations.effective_counts`). The latent is a DTC sparse GP
(Quiñonero-Candela & Rasmussen 2005) on ``m = k**d`` inducing points ``u`` on a regular
lattice over the halo box, in whitened form: with ``K_uu = L Lᵀ`` and the feature of a
point ``φ(x) = L⁻¹ k_u(x)``,

.. math::

    A = I + σ_n^{-2} \sum_i w_i φ_i φ_iᵀ,\quad b = σ_n^{-2} \sum_i w_i y_i φ_i,

    μ(x) = φ(x)ᵀ A^{-1} b,\qquad
    σ^2(x) = k(x, x) − |φ(x)|^2 + φ(x)ᵀ A^{-1} φ(x).

Far from any observation ``A → I`` and the posterior returns to the prior ``(0, σf²)``;
with the lattice at the observed points it is the exact GP on them.

**Why it is fast.** The voxel centres of every leaf's halo box and the lattice sit at
the same offsets from the leaf's corner in every leaf, so ``φ`` of every halo voxel
(``Φ``, ``H × m``) and of every leaf voxel (``Ψ``, ``V × m``) are *one pair of tables
for the whole map* (:func:`lattice_tables`): fitting a leaf evaluates no kernel at
all. It is ``Φ_vᵀ Φ_v`` over the leaf's observed voxels, one Cholesky of ``m × m``
and two small products, stacked over many leaves into a few BLAS calls
(:func:`lattice_posterior`). The posterior is a pure function of the leaf's counts and
kept returns.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dpotrf, dtrtri

from octolgp.config import Hyperparameters
from octolgp.gp import lattice_kernel
from octolgp.gp.kernels import matern32
from octolgp.scan import FloatArray

IntArray = NDArray[np.int64]

JITTER = 1e-8
"""Relative jitter on the lattice covariance ``K_uu`` (its Cholesky is taken once)."""

MIN_NOISE = 1e-8
"""Floor of ``σn² / σf²`` in the lattice engine: with a vanishing noise variance the
precision ``1 / σn²`` would overflow ``A``; the floor keeps it finite."""


@dataclass(frozen=True, slots=True)
class LatticeGeometry:
    """Where the voxels and the inducing lattice of one leaf sit, in voxels.

    Attributes
    ----------
    dim : int
        2 or 3.
    side : int
        Voxels along a leaf's edge.
    halo : int
        Voxels the halo box adds on every side.
    k : int
        Inducing points per axis (``m = k**dim``).
    resolution : float
        Voxel edge, metres.
    """

    dim: int
    side: int
    halo: int
    k: int
    resolution: float

    @property
    def box(self) -> int:
        """Voxels along the halo box's edge, ``side + 2 halo``."""
        return self.side + 2 * self.halo

    @property
    def n_halo(self) -> int:
        """Voxels in the halo box, ``H = box**dim``."""
        return int(self.box**self.dim)

    @property
    def n_inducing(self) -> int:
        """Inducing points, ``m = k**dim``."""
        return int(self.k**self.dim)

    def halo_centres(self) -> FloatArray:
        """Halo-box voxel centres relative to the leaf's lower corner, (H, d), x fastest."""
        steps = (np.arange(self.box) - self.halo + 0.5) * self.resolution
        return _lattice(steps, self.dim)

    def leaf_centres(self) -> FloatArray:
        """The leaf's own voxel centres relative to its lower corner, (V, d), x fastest."""
        return _lattice((np.arange(self.side) + 0.5) * self.resolution, self.dim)

    def inducing_points(self) -> FloatArray:
        """Inducing points at the cell centres of a ``k``-lattice over the halo box, (m, d)."""
        edge = self.box * self.resolution
        steps = -self.halo * self.resolution + (np.arange(self.k) + 0.5) * (edge / self.k)
        return _lattice(steps, self.dim)


def _lattice(steps: np.ndarray, dim: int) -> FloatArray:
    """All points of ``steps`` per axis, (len**dim, dim), x fastest."""
    grids = np.meshgrid(*([steps] * dim), indexing="ij")
    return np.stack([g.ravel(order="F") for g in grids], axis=1)


def inducing_per_axis(
    box_edge: float, length_scale: float, spacing: float, k_min: int, k_max: int
) -> int:
    """Lattice points per axis so that they are at most ``spacing × length_scale`` apart.

    A long length scale does not make a posterior smooth when the noise is small (it
    still interpolates its data), so the lattice never gets coarser than ``k_min``.

    Parameters
    ----------
    box_edge : float
        Halo box edge, metres.
    length_scale : float
        Kernel length scale, metres.
    spacing : float
        Largest lattice spacing as a fraction of the length scale.
    k_min, k_max : int
        Bounds (cost grows as ``k**(3 d)``).
    """
    k = math.ceil(box_edge / (spacing * length_scale) - 1e-9)
    return int(min(max(k, k_min, 2), k_max))


@dataclass(frozen=True, slots=True)
class LatticeTables:
    """The constant tables of a map's lattice leaf GP (read-only arrays).

    Attributes
    ----------
    geometry : LatticeGeometry
    phi : ndarray of shape (H, m)
        Whitened features ``L⁻¹ k_u(x)`` of the halo-box voxel centres.
    pairs : ndarray of shape (H, m (m + 1) / 2)
        ``φ_i φ_j`` (``i <= j``, row-major upper triangle) of each halo voxel, so that
        one matrix product gives the upper triangles of many leaves' ``Φᵀ W Φ``.
    psi_t : ndarray of shape (m, V)
        Features of the leaf's own voxel centres, transposed.
    residual : ndarray of shape (V,)
        ``k(x, x) − |ψ(x)|²``: prior variance the lattice cannot explain, >= 0.
    noise_variance : float
        ``σn²`` (at least ``MIN_NOISE σf²``).
    inducing : ndarray of shape (m, d)
        The lattice, relative to the leaf's lower corner, metres.
    chol : ndarray of shape (m, m)
        Lower Cholesky factor of ``K_uu`` (with its jitter).
    hp : Hyperparameters
        The kernel of the tables (for the features of returns at their positions).
    """

    geometry: LatticeGeometry
    phi: FloatArray
    pairs: FloatArray
    psi_t: FloatArray
    residual: FloatArray
    noise_variance: float
    inducing: FloatArray
    chol: FloatArray
    hp: Hyperparameters

    def features(self, points: FloatArray) -> FloatArray:
        """Whitened features ``L⁻¹ k_u(x)`` of points relative to a leaf's corner, (n, m)."""
        out: FloatArray = solve_triangular(
            self.chol, _kernel(self.inducing, points, self.hp), lower=True
        ).T
        return out


def _frozen(a: np.ndarray) -> FloatArray:
    out = np.ascontiguousarray(a, dtype=np.float64)
    out.setflags(write=False)
    return out


def _kernel(A: FloatArray, B: FloatArray, hp: Hyperparameters) -> FloatArray:
    """Matérn 3/2 between point sets ``A`` (n, d) and ``B`` (p, d)."""
    r = np.sqrt(((A[:, None, :] - B[None, :, :]) ** 2).sum(-1))
    return matern32(r, hp.length_scale, hp.signal_variance)


def lattice_tables(geometry: LatticeGeometry, hp: Hyperparameters) -> LatticeTables:
    """Build the feature tables of a lattice (once per map and hyperparameters).

    Parameters
    ----------
    geometry : LatticeGeometry
    hp : Hyperparameters
        Uses ``length_scale``, ``signal_variance`` and ``noise_variance``.

    Returns
    -------
    LatticeTables
    """
    U = geometry.inducing_points()
    Kuu = _kernel(U, U, hp)
    Kuu[np.diag_indices_from(Kuu)] += JITTER * hp.signal_variance
    L = np.linalg.cholesky(Kuu)
    phi = solve_triangular(L, _kernel(U, geometry.halo_centres(), hp), lower=True).T
    psi = solve_triangular(L, _kernel(U, geometry.leaf_centres(), hp), lower=True).T
    iu, ju = np.triu_indices(U.shape[0])
    residual = np.maximum(hp.signal_variance - (psi * psi).sum(1), 0.0)
    return LatticeTables(
        geometry,
        _frozen(phi),
        _frozen(phi[:, iu] * phi[:, ju]),
        _frozen(psi.T),
        _frozen(residual),
        max(hp.noise_variance, MIN_NOISE * hp.signal_variance),
        _frozen(U),
        _frozen(L),
        hp,
    )


CHOLESKY_INVERSE_FROM = 128
"""Lattice size from which :func:`inverse_cholesky_factors` works leaf by leaf through
LAPACK (``potrf`` + ``trtri``) instead of a batched Cholesky and forward substitution.
Measured on one thread (ms per stack): m = 8, 1000 matrices: loop 2.1-3.9, batched
1.0-1.2; m = 27, 1000: 7.0-7.7 vs 9.6-10.4; m = 64, 500: 23 vs 42-46; m = 144, 240: 55
vs 234. Both paths agree to rounding (``tests/test_lattice.py``)."""

COMPILED_UP_TO = 64
"""Largest lattice (``m``) that :func:`lattice_posterior` fits with the compiled kernel
by default. The kernel skips unobserved voxels and keeps each leaf in cache, which wins
on the 3D lattices (``m`` 27 and 64, 64 leaf voxels); from ``m = 64`` in 2D (256 leaf
voxels) the stacked BLAS products are as fast, and faster beyond (BENCHMARKS.md,
"Lattice engine")."""

CHUNK_BYTES = 16 << 20
"""Bytes of the largest transient array of one chunk of leaves in :func:`lattice_posterior`
(bounded chunks reuse freed memory instead of faulting in fresh pages)."""


HitPoints = list[tuple[FloatArray, FloatArray]]
"""Per leaf, its returns' positions relative to its lower corner (h, d) and weights (h,)."""


@dataclass(frozen=True, slots=True)
class Returns:
    """Many leaves' returns at their measured positions, stored flat (leaf after leaf).

    Attributes
    ----------
    points : ndarray of shape (R, d)
        Positions relative to the owning leaf's lower corner, metres.
    weights : ndarray of shape (R,)
        Precision multiplier of each return (its voxel's return count).
    counts : ndarray of int64, shape (L,)
        Returns per leaf; leaf ``j``'s are rows ``offsets[j]:offsets[j + 1]``.
    """

    points: FloatArray
    weights: FloatArray
    counts: IntArray

    @classmethod
    def from_list(cls, points: HitPoints, dim: int) -> Returns:
        """The flat form of a per-leaf list of (positions, weights)."""
        counts = np.array([p.shape[0] for p, _ in points], dtype=np.int64)
        if not points or counts.sum() == 0:
            return cls(np.zeros((0, dim)), np.zeros(0), counts)
        return cls(
            np.concatenate([p for p, _ in points]),
            np.concatenate([w for _, w in points]).astype(np.float64),
            counts,
        )

    @property
    def offsets(self) -> IntArray:
        """Row of each leaf's first return, and the total at the end, (L + 1,)."""
        out: IntArray = np.r_[0, np.cumsum(self.counts)].astype(np.int64)
        return out

    def leaves(self, lo: int, hi: int) -> Returns:
        """The returns of leaves ``lo:hi``."""
        at = self.offsets
        rows = slice(int(at[lo]), int(at[hi]))
        return Returns(self.points[rows], self.weights[rows], self.counts[lo:hi])


def lattice_posterior(
    tables: LatticeTables,
    hits: NDArray[np.integer],
    frees: NDArray[np.integer],
    free_weight: float = 1.0,
    hit_points: HitPoints | Returns | None = None,
    *,
    compiled: bool | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Latent posterior at the voxel centres of many leaves at once.

    Parameters
    ----------
    tables : LatticeTables
    hits, frees : ndarray of int, shape (L, H)
        Per leaf and halo-box voxel (x fastest), how often the voxel was observed
        with a return and free.
    free_weight : float
        Precision multiplier of a free observation.
    hit_points : Returns or list of (ndarray, ndarray), optional
        Per leaf, the returns at their measured positions (relative to the leaf's
        lower corner) with their weights; then ``hits`` is not used. By default each
        return sits at its voxel's centre.
    compiled : bool, optional
        Whether to run the compiled kernel (:mod:`octolgp.gp.lattice_kernel`, leaf by
        leaf) or the stacked numpy products; by default the kernel where numba imports
        and ``m <= COMPILED_UP_TO``. The two agree to rounding.

    Returns
    -------
    mean, var : ndarray of shape (L, V)
        Latent mean and variance (without the noise) at each leaf's voxel centres.
    """
    n_leaves = hits.shape[0]
    m, n_vox = tables.psi_t.shape
    returns = (
        Returns.from_list(hit_points, tables.geometry.dim)
        if isinstance(hit_points, list)
        else hit_points
    )
    if compiled is None:
        compiled = lattice_kernel.AVAILABLE and m <= COMPILED_UP_TO
    if compiled:
        prec = 1.0 / tables.noise_variance
        if returns is None:
            points, weights = np.zeros((0, tables.geometry.dim)), np.zeros(0)
            offsets = np.zeros(n_leaves + 1, dtype=np.int64)
        else:
            points, weights, offsets = returns.points, returns.weights * prec, returns.offsets
        return lattice_kernel.leaf_posteriors(
            None if returns is not None else hits,
            frees,
            free_weight,
            prec,
            tables.phi,
            tables.pairs,
            tables.psi_t,
            tables.residual,
            tables.inducing,
            tables.chol,
            tables.hp.length_scale,
            tables.hp.signal_variance,
            points,
            weights,
            offsets,
        )
    per_leaf = 8 * max(m * m, m * n_vox, tables.pairs.shape[1])
    step = max(1, CHUNK_BYTES // per_leaf)
    mean = np.empty((n_leaves, n_vox))
    var = np.empty((n_leaves, n_vox))
    for lo in range(0, n_leaves, step):  # one chunk of leaves per iteration
        hi = min(lo + step, n_leaves)
        mean[lo:hi], var[lo:hi] = _posterior_chunk(
            tables,
            hits[lo:hi],
            frees[lo:hi],
            free_weight,
            None if returns is None else returns.leaves(lo, hi),
        )
    return mean, var


def _posterior_chunk(
    tables: LatticeTables,
    hits: NDArray[np.integer],
    frees: NDArray[np.integer],
    free_weight: float,
    returns: Returns | None,
) -> tuple[FloatArray, FloatArray]:
    """:func:`lattice_posterior` of one chunk of leaves: a few large matrix products.

    With ``A = L Lᵀ`` and ``R = L⁻¹``: ``μ = (R Ψᵀ)ᵀ (R b)`` and
    ``ψᵀ A⁻¹ ψ = |R ψ|²``, so no inverse of ``A`` is formed.
    """
    n = hits.shape[0]
    m, n_vox = tables.psi_t.shape
    prec = 1.0 / tables.noise_variance
    h = hits.astype(np.float64) if returns is None else np.zeros(hits.shape)
    f = frees * free_weight
    upper = ((h + f) * prec) @ tables.pairs  # (n, m (m+1)/2): upper triangles of Φᵀ W Φ
    b = ((h - f) * prec) @ tables.phi  # (n, m)
    if returns is not None:
        _add_points(upper, b, tables, returns, prec)
    A = np.take(upper, _symmetric_index(m), axis=1).reshape(n, m, m)
    A[:, np.arange(m), np.arange(m)] += 1.0
    R = inverse_cholesky_factors(A)  # A >= I, so well conditioned
    c = np.matmul(R, b[:, :, None])[:, :, 0]  # (n, m)
    Z = (R.reshape(n * m, m) @ tables.psi_t).reshape(n, m, n_vox)
    mean = np.matmul(c[:, None, :], Z)[:, 0, :]
    Z *= Z
    var = tables.residual + Z.sum(1)
    return mean, var


@functools.lru_cache(maxsize=8)
def _symmetric_index(m: int) -> IntArray:
    """Per entry of an ``m x m`` matrix, its place in the row-major upper triangle."""
    iu, ju = np.triu_indices(m)
    place = np.empty((m, m), dtype=np.int64)
    place[iu, ju] = np.arange(iu.size)
    place[ju, iu] = np.arange(iu.size)
    out: IntArray = place.ravel()
    out.setflags(write=False)
    return out


def inverse_cholesky_factors(A: FloatArray) -> FloatArray:
    """``L⁻¹`` of the lower Cholesky factor ``L`` of each of a stack of SPD matrices.

    Parameters
    ----------
    A : ndarray of shape (n, m, m)
        Symmetric positive definite; may be overwritten.

    Returns
    -------
    ndarray of shape (n, m, m)
        Lower triangular ``R`` with ``A = L Lᵀ``, ``R = L⁻¹`` (so ``A⁻¹ = Rᵀ R``).

    Raises
    ------
    numpy.linalg.LinAlgError
        If a matrix is not positive definite.
    """
    n, m, _ = A.shape
    if m >= CHOLESKY_INVERSE_FROM:
        for j in range(n):  # one LAPACK call pair per matrix
            factor, info = dpotrf(A[j], lower=1, clean=1)
            if info == 0:
                factor, info = dtrtri(factor, lower=1, overwrite_c=1)
            if info != 0:
                raise np.linalg.LinAlgError(f"matrix {j} is not positive definite")
            A[j] = factor
        return A
    L = np.linalg.cholesky(A)
    R = np.zeros_like(L)
    inv_diag = 1.0 / np.diagonal(L, axis1=1, axis2=2)
    for i in range(m):  # forward substitution, row i of L⁻¹ for every matrix at once
        row = -np.matmul(L[:, i : i + 1, :i], R[:, :i, :])[:, 0, :]
        row[:, i] += 1.0
        R[:, i, :] = row * inv_diag[:, i : i + 1]
    return R


def _add_points(
    upper: FloatArray, b: FloatArray, tables: LatticeTables, returns: Returns, prec: float
) -> None:
    """Add returns at their positions to the leaves' ``A`` (its upper triangle) and ``b``.

    Each return adds ``w φφᵀ`` to its leaf's ``A`` and ``w φ`` to its ``b``. Leaves are
    grouped by their number of returns (up to 1, 2, 4, 8, ...) and each group's ``Gᵀ G``
    is one batched product, so padding at most doubles the work. In place.
    """
    counts = returns.counts
    if int(counts.sum()) == 0:
        return
    m = b.shape[1]
    iu, ju = np.triu_indices(m)
    w = returns.weights * prec
    F = tables.features(returns.points)  # (total, m)
    start = returns.offsets[:-1]
    width = np.zeros(counts.size, dtype=np.int64)  # padded size: the next power of two
    has = counts > 0
    width[has] = 1 << np.ceil(np.log2(counts[has])).astype(np.int64)
    for size in np.unique(width[has]).tolist():  # one batched product per group
        group = np.flatnonzero(width == size)
        slot = np.arange(size)
        rows = start[group][:, None] + slot  # (g, size) rows of F, padded
        valid = slot < counts[group][:, None]
        rows = np.where(valid, rows, 0)
        root = np.where(valid, np.sqrt(w[rows]), 0.0)
        G = F[rows] * root[:, :, None]  # (g, size, m)
        Gt = G.transpose(0, 2, 1)
        upper[group] += np.matmul(Gt, G)[:, iu, ju]
        b[group] += np.matmul(Gt, root[:, :, None])[:, :, 0]


def dtc_reference(
    inducing: FloatArray,
    points: FloatArray,
    y: FloatArray,
    weights: FloatArray,
    test: FloatArray,
    hp: Hyperparameters,
) -> tuple[FloatArray, FloatArray]:
    """The DTC posterior written out directly, for one leaf (the reference of the tests).

    With ``Λ = diag(weights) / σn²`` (a point of weight ``w`` has noise ``σn² / w``):
    ``Σ = (K_uu + K_uf Λ K_fu)⁻¹``, ``μ = K_*u Σ K_uf Λ y``,
    ``σ² = k_** − K_*u K_uu⁻¹ K_u* + K_*u Σ K_u*`` (R&W §8.3.3).

    Parameters
    ----------
    inducing : ndarray of shape (m, d)
    points : ndarray of shape (n, d)
        Observation points.
    y : ndarray of shape (n,)
    weights : ndarray of shape (n,)
        Precision multiplier of each observation.
    test : ndarray of shape (t, d)
    hp : Hyperparameters

    Returns
    -------
    mean, var : ndarray of shape (t,)
    """
    Kuu = _kernel(inducing, inducing, hp)
    Kuu[np.diag_indices_from(Kuu)] += JITTER * hp.signal_variance
    Kuf = _kernel(inducing, points, hp)
    Ksu = _kernel(test, inducing, hp)
    lam = weights / hp.noise_variance
    S = np.linalg.inv(Kuu + (Kuf * lam) @ Kuf.T)
    mean = Ksu @ S @ Kuf @ (lam * y)
    q = np.einsum("ij,ji->i", Ksu, np.linalg.solve(Kuu, Ksu.T))
    var = hp.signal_variance - q + np.einsum("ij,ji->i", Ksu, S @ Ksu.T)
    return mean, var
