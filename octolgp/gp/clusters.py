"""One local GP per cluster: fit them all, predict each point by its nearest cluster.

The paper's OM_LGP (Kim & Kim 2013, §III-B): clusters come from
:func:`octolgp.partition.partition` with overlapping extended boxes; each is fitted
on its own items and a query point is predicted by the GP of the nearest cluster
centre. Used by the batch map (:mod:`octolgp.batch.lgp`) and inside online leaves
that hold more items than ``OnlineConfig.max_leaf_items``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree

from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.quadrature import cluster_items, quadrature_spacing
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


def predict_nearest(
    tree: cKDTree,
    gps: list[LocalGP],
    X: FloatArray,
    signal_variance: float,
    n_jobs: int = 1,
) -> tuple[FloatArray, FloatArray]:
    """Latent mean and variance at points, each from the GP of its nearest cluster centre.

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over the cluster centres, in the order of ``gps``.
    gps : list of LocalGP
    X : ndarray of shape (q, d)
        Query points, metres, world frame.
    signal_variance : float
        The prior variance, returned where there is no GP.
    n_jobs : int
        Threads over clusters; the result does not depend on it.

    Returns
    -------
    mean, var : ndarray of shape (q,)
    """
    mean = np.zeros(X.shape[0])
    var = np.full(X.shape[0], signal_variance)
    if not gps or X.shape[0] == 0:
        return mean, var
    _, owner = tree.query(X)
    order = np.argsort(owner, kind="stable")
    cuts = np.flatnonzero(np.diff(owner[order])) + 1
    groups = np.split(order, cuts)

    def predict(idx: np.ndarray) -> tuple[np.ndarray, FloatArray, FloatArray]:
        m, v = predict_latent(gps[int(owner[idx[0]])], X[idx])
        return idx, m, v

    if n_jobs > 1 and len(groups) > 1:
        with ThreadPoolExecutor(max_workers=n_jobs) as pool:
            results = list(pool.map(predict, groups))
    else:
        results = [predict(g) for g in groups]
    for idx, m, v in results:  # one iteration per cluster
        mean[idx], var[idx] = m, v
    return mean, var


def cluster_tree(clusters: list[Cluster], dim: int) -> cKDTree:
    """A k-d tree over the cluster centres (in cluster order)."""
    return cKDTree(np.array([c.centre for c in clusters]).reshape(-1, dim))
