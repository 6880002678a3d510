"""The lattice posterior compiled leaf by leaf (numba): the fast path of the lattice GP.

:func:`octolgp.gp.lattice.lattice_posterior` stacks many leaves into a few dense
matrix products. Most leaves of a 3D scan observe a small share of their halo box (a
far leaf sees a few beams through it), so the dense product over every halo voxel and
the stacked intermediates (each leaf's ``A``, ``L⁻¹`` and ``L⁻¹ Ψᵀ``, written out and read
back) cost more than the arithmetic a leaf needs. This kernel does one leaf at a time
in registers and cache:

1. ``A = I + Σ_v w_v φ_v φ_vᵀ`` and ``b = Σ_v w_v y_v φ_v`` over the observed voxels only
   (one contiguous pass over the voxel's packed products ``φ_a φ_c``), then the returns
   at their positions, whose features ``L⁻¹ k_u(x)`` (the Matérn 3/2 to each lattice
   point, then a forward substitution) are computed here rather than stacked for all
   leaves beforehand, upper triangle;
2. ``A = Uᵀ U`` in place (right-looking Cholesky, rows contiguous);
3. ``Z = U⁻ᵀ Ψᵀ`` and ``c = U⁻ᵀ b`` by forward substitution over rows of length ``V``;
4. ``μ = Zᵀ c`` and ``σ² = residual + Σ_a Z_a²``.

The arithmetic is that of the numpy path in another order; the two agree to rounding
(``tests/test_lattice_kernel.py``). The kernel releases the GIL, so the engine's thread
pool runs chunks of leaves in parallel. Without numba (:data:`AVAILABLE` false) the
numpy path serves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

from octolgp.scan import FloatArray

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether the compiled kernel can run (numba is installed; it is imported on first use)."""


def _leaf_posteriors(
    h: NDArray[np.integer],
    f: NDArray[np.integer],
    free_weight: float,
    prec: float,
    phi: FloatArray,
    pairs: FloatArray,
    psi_t: FloatArray,
    residual: FloatArray,
    inducing: FloatArray,
    inv_chol_t: FloatArray,
    kernel: FloatArray,
    points: FloatArray,
    weights: FloatArray,
    offsets: NDArray[np.int64],
    mean: FloatArray,
    var: FloatArray,
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """Fill ``mean`` and ``var`` (n, V) of ``n`` leaves (see the module docstring)."""
    n, n_halo = f.shape
    has_h = h.shape[0] > 0
    m = phi.shape[1]
    dim = inducing.shape[1]
    n_vox = psi_t.shape[1]
    n_pairs = pairs.shape[1]
    scale, sigma2 = kernel[0], kernel[1]  # sqrt(3) / length scale, signal variance
    A = np.empty((m, m))
    b = np.empty(m)
    upper = np.empty(n_pairs)
    p = np.empty(m)
    kx = np.empty(m)
    Z = np.empty((m, n_vox))
    for j in range(n):  # one leaf per iteration
        upper[:] = 0.0
        b[:] = 0.0
        for v in range(n_halo):  # the observed halo voxels, at their centres
            hv = float(h[j, v]) if has_h else 0.0
            fv = f[j, v] * free_weight
            w = (hv + fv) * prec
            if w == 0.0:
                continue
            y = (hv - fv) * prec
            q = phi[v]
            for a in range(m):
                b[a] += y * q[a]
            q = pairs[v]
            for c in range(n_pairs):  # the upper triangle of w φ φᵀ, packed
                upper[c] += w * q[c]
        s = 0
        for a in range(m):  # A = I + the packed upper triangle
            row = A[a]
            for c in range(a, m):
                row[c] = upper[s]
                s += 1
            row[a] += 1.0
        for r in range(offsets[j], offsets[j + 1]):  # the returns at their positions
            for a in range(m):  # k_u(x): Matérn 3/2 to each lattice point
                d2 = 0.0
                for e in range(dim):
                    t = inducing[a, e] - points[r, e]
                    d2 += t * t
                x = scale * np.sqrt(d2)
                kx[a] = sigma2 * (1.0 + x) * np.exp(-x)
            p[:] = 0.0
            for c in range(m):  # φ = L⁻¹ k_u(x), column by column of L⁻¹ (rows of its transpose)
                kc = kx[c]
                lc = inv_chol_t[c]
                for a in range(m):
                    p[a] += kc * lc[a]
            w = weights[r]
            for a in range(m):  # whole rows (the part below the diagonal is never read)
                wa = w * p[a]
                b[a] += wa
                row = A[a]
                for c in range(m):
                    row[c] += wa * p[c]
        for k in range(m):  # A = Uᵀ U, U in the upper triangle
            rk = A[k]
            d = np.sqrt(rk[k])
            rk[k] = d
            inv = 1.0 / d
            for c in range(k + 1, m):
                rk[c] *= inv
            for a in range(k + 1, m):
                t = rk[a]
                ra = A[a]
                for c in range(a, m):
                    ra[c] -= t * rk[c]
        Z[:, :] = psi_t
        for i in range(m):  # Uᵀ Z = Ψᵀ and Uᵀ c = b, forward substitution by rows
            inv = 1.0 / A[i, i]
            b[i] *= inv
            zi = Z[i]
            for t in range(n_vox):
                zi[t] *= inv
            for a in range(i + 1, m):
                u = A[i, a]
                b[a] -= u * b[i]
                za = Z[a]
                for t in range(n_vox):
                    za[t] -= u * zi[t]
        mj = mean[j]
        vj = var[j]
        for t in range(n_vox):
            mj[t] = 0.0
            vj[t] = residual[t]
        for a in range(m):  # μ = Zᵀ c, σ² = residual + column sums of Z²
            ca = b[a]
            za = Z[a]
            for t in range(n_vox):
                z = za[t]
                mj[t] += ca * z
                vj[t] += z * z


@functools.cache
def _compiled() -> Callable[..., None]:
    """The kernel compiled by numba (cached on disk beside the module after the first run).

    Fused multiply-adds are allowed (``fastmath={"contract"}``); nothing is reordered
    and no assumption about NaN or infinity is made.
    """
    from numba import njit

    out: Callable[..., None] = njit(cache=True, nogil=True, fastmath={"contract"})(_leaf_posteriors)
    return out


def leaf_posteriors(
    h: NDArray[np.integer] | None,
    f: NDArray[np.integer],
    free_weight: float,
    prec: float,
    phi: FloatArray,
    pairs: FloatArray,
    psi_t: FloatArray,
    residual: FloatArray,
    inducing: FloatArray,
    chol: FloatArray,
    length_scale: float,
    signal_variance: float,
    points: FloatArray,
    weights: FloatArray,
    offsets: NDArray[np.int64],
) -> tuple[FloatArray, FloatArray]:
    """Latent mean and variance at the voxel centres of ``n`` leaves, compiled.

    Parameters
    ----------
    h, f : ndarray of int, shape (n, H)
        Per leaf and halo voxel: the return count and the free count of observations
        at the voxel centre (targets +1 and −1); ``h`` ``None`` when the returns are
        all given at their positions.
    free_weight : float
        Precision multiplier of a free observation.
    prec : float
        ``1 / σn²``.
    phi : ndarray of shape (H, m)
        Whitened features of the halo voxel centres.
    pairs : ndarray of shape (H, m (m + 1) / 2)
        Their products ``φ_a φ_c`` (``a <= c``, row-major upper triangle).
    psi_t : ndarray of shape (m, V)
        Whitened features of the leaf voxel centres, transposed.
    residual : ndarray of shape (V,)
        ``k(x, x) − |ψ(x)|²``.
    inducing : ndarray of shape (m, d)
        The lattice relative to a leaf's lower corner, metres.
    chol : ndarray of shape (m, m)
        Lower Cholesky factor ``L`` of ``K_uu``: a return's feature is ``L⁻¹ k_u(x)``.
    length_scale, signal_variance : float
        The Matérn 3/2 kernel of ``k_u``.
    points : ndarray of shape (R, d)
        The returns at their positions relative to their leaf's lower corner (target
        +1), metres, leaf after leaf.
    weights : ndarray of shape (R,)
        Their precisions (weight ``/ σn²``).
    offsets : ndarray of int64, shape (n + 1,)
        Leaf ``j``'s returns are rows ``offsets[j]:offsets[j + 1]``.

    Returns
    -------
    mean, var : ndarray of shape (n, V)

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled lattice kernel needs numba")
    n = f.shape[0]
    n_vox = psi_t.shape[1]
    mean = np.empty((n, n_vox))
    var = np.empty((n, n_vox))
    c = np.ascontiguousarray
    kernel = np.array([np.sqrt(3.0) / length_scale, signal_variance])
    _compiled()(
        np.zeros((0, 0), dtype=f.dtype) if h is None else c(h),
        c(f),
        float(free_weight),
        float(prec),
        c(phi),
        c(pairs),
        c(psi_t),
        c(residual),
        c(inducing, dtype=np.float64),
        c(solve_triangular(chol, np.eye(chol.shape[0]), lower=True).T),
        kernel,
        c(points, dtype=np.float64).reshape(-1, inducing.shape[1]),
        c(weights, dtype=np.float64),
        c(offsets, dtype=np.int64),
        mean,
        var,
    )
    return mean, var
