"""The paper's method, OM_LGP: overlapping local GPs, nearest-cluster prediction."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from octolgp.batch.gpmap import GPMap, cluster_items, quadrature_spacing
from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.regression import LocalGP, fit_local_gp, predict_latent
from octolgp.partition import Cluster
from octolgp.scan import FloatArray
from octolgp.training import TrainingData


def fit_clusters(
    data: TrainingData,
    clusters: list[Cluster],
    config: MapConfig,
    hp: Hyperparameters,
    n_jobs: int = 1,
) -> list[LocalGP]:
    """Fit one local GP per cluster (threads share the work: LAPACK releases the GIL).

    Results do not depend on ``n_jobs``.
    """
    spacing = quadrature_spacing(config, hp.length_scale)

    def fit(cluster: Cluster) -> LocalGP:
        items, y = cluster_items(data, cluster, config, spacing)
        return fit_local_gp(items, y, hp)

    if n_jobs <= 1 or len(clusters) < 2:
        return [fit(c) for c in clusters]
    with ThreadPoolExecutor(max_workers=n_jobs) as pool:
        return list(pool.map(fit, clusters))


@dataclass
class LocalGPMap(GPMap):
    """OM_LGP: each query point is predicted by the local GP of the nearest cluster centre.

    Attributes
    ----------
    clusters : list of Cluster
    gps : list of LocalGP
        One per cluster, fitted on its extended training set.
    """

    clusters: list[Cluster] = field(default_factory=list)
    gps: list[LocalGP] = field(default_factory=list)
    n_jobs: int = 1

    def __post_init__(self) -> None:
        centres = np.array([c.centre for c in self.clusters]).reshape(-1, self.config.dim)
        self._tree = cKDTree(centres)

    def _latent(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        with threadpool_limits(limits=1):
            return self._latent_nearest(X)

    def _latent_nearest(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        mean = np.zeros(X.shape[0])
        var = np.full(X.shape[0], self.hyperparameters.signal_variance)
        if not self.gps or X.shape[0] == 0:
            return mean, var
        _, owner = self._tree.query(X)
        order = np.argsort(owner, kind="stable")
        cuts = np.flatnonzero(np.diff(owner[order])) + 1
        groups = np.split(order, cuts)

        def predict(idx: np.ndarray) -> tuple[np.ndarray, FloatArray, FloatArray]:
            m, v = predict_latent(self.gps[int(owner[idx[0]])], X[idx])
            return idx, m, v

        if self.n_jobs > 1 and len(groups) > 1:
            with ThreadPoolExecutor(max_workers=self.n_jobs) as pool:
                results = list(pool.map(predict, groups))
        else:
            results = [predict(g) for g in groups]
        for idx, m, v in results:  # one iteration per cluster
            mean[idx], var[idx] = m, v
        return mean, var
