"""Kim & Kim Fig. 2 in 1D: global GP vs disjoint vs overlapping local GPs.

Local GPs predict each point from the nearest cluster, so the prediction can jump
where the nearest cluster changes. Overlap (sharing data near borders) shrinks the
jump. The jump at a border ``b`` between clusters ``i`` and ``i + 1`` is
``|μ_i(b) − μ_{i+1}(b)|``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolgp.config import Hyperparameters
from octolgp.gp.quadrature import points_set
from octolgp.gp.regression import LocalGP, fit_local_gp, predict_latent
from octolgp.scan import FloatArray


@dataclass(frozen=True)
class Fig2Result:
    """Mean absolute border jump for disjoint and overlapping local GPs."""

    jump_disjoint: float
    jump_overlap: float
    rmse_global: float
    rmse_disjoint: float
    rmse_overlap: float


def _truth(x: FloatArray) -> FloatArray:
    return np.sin(x) + 0.5 * np.sin(2.3 * x + 0.4)


def _local_gps(
    X: FloatArray, y: FloatArray, edges: FloatArray, overlap: float, hp: Hyperparameters
) -> list[LocalGP]:
    gps = []
    for lo, hi in itertools.pairwise(edges):  # one GP per cluster
        margin = overlap * (hi - lo)
        m = (X[:, 0] >= lo - margin) & (X[:, 0] <= hi + margin)
        gps.append(fit_local_gp(points_set(X[m]), y[m], hp))
    return gps


def _predict_nearest(gps: list[LocalGP], edges: FloatArray, x: FloatArray) -> FloatArray:
    owner = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(gps) - 1)
    out = np.empty_like(x)
    for k, gp in enumerate(gps):
        sel = owner == k
        out[sel] = predict_latent(gp, x[sel, None])[0]
    return out


def run_fig2(
    out_png: Path | None = None, seed: int = 0, n_clusters: int = 4, overlap: float = 0.2
) -> Fig2Result:
    """Fit the three models on noisy 1D samples, measure border jumps, plot.

    Parameters
    ----------
    out_png : Path, optional
        Where to write the figure (matplotlib, Agg).
    seed : int
    n_clusters : int
        Equal-width clusters over [0, 10].
    overlap : float
        Extension of each cluster on each side, as a fraction of its width.
    """
    rng = np.random.default_rng(seed)
    X = np.sort(rng.uniform(0.0, 10.0, 80))[:, None]
    y = _truth(X[:, 0]) + rng.normal(0.0, 0.1, X.shape[0])
    hp = Hyperparameters(length_scale=1.5, signal_variance=1.0, noise_variance=0.01)
    edges = np.linspace(0.0, 10.0, n_clusters + 1)
    borders = edges[1:-1]
    xs = np.linspace(0.0, 10.0, 1001)

    glob = fit_local_gp(points_set(X), y, hp)
    mu_global = predict_latent(glob, xs[:, None])[0]
    disjoint = _local_gps(X, y, edges, 0.0, hp)
    overlapping = _local_gps(X, y, edges, overlap, hp)

    def jump(gps: list[LocalGP]) -> float:
        left = np.array(
            [predict_latent(gps[i], borders[i : i + 1, None])[0][0] for i in range(len(borders))]
        )
        right = np.array(
            [
                predict_latent(gps[i + 1], borders[i : i + 1, None])[0][0]
                for i in range(len(borders))
            ]
        )
        return float(np.mean(np.abs(left - right)))

    mu_dis = _predict_nearest(disjoint, edges, xs)
    mu_ov = _predict_nearest(overlapping, edges, xs)
    truth = _truth(xs)
    rmse = [float(np.sqrt(np.mean((m - truth) ** 2))) for m in (mu_global, mu_dis, mu_ov)]
    result = Fig2Result(jump(disjoint), jump(overlapping), *rmse)
    if out_png is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(13, 3.4), sharey=True)
        titles = (
            "global GP",
            f"disjoint local GPs (jump {result.jump_disjoint:.3f})",
            f"overlapping local GPs (jump {result.jump_overlap:.3f})",
        )
        for ax, mu, title in zip(axes, (mu_global, mu_dis, mu_ov), titles, strict=True):
            ax.plot(xs, truth, color="0.6", lw=1, label="truth")
            ax.plot(X[:, 0], y, ".", ms=3, color="k", label="data")
            ax.plot(xs, mu, color="C3", lw=1.5, label="GP mean")
            for b in borders:
                ax.axvline(b, color="C0", ls=":", lw=0.8)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("x")
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out_png, dpi=120)
        plt.close(fig)
    return result
