"""The paper's method, OM_LGP: overlapping local GPs, nearest-cluster prediction."""

from __future__ import annotations

from dataclasses import dataclass, field

from threadpoolctl import threadpool_limits

from octolgp.batch.gpmap import GPMap
from octolgp.gp.clusters import cluster_tree, fit_clusters, predict_nearest
from octolgp.gp.regression import LocalGP
from octolgp.partition import Cluster
from octolgp.scan import FloatArray

__all__ = ["LocalGPMap", "fit_clusters"]


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
        self._tree = cluster_tree(self.clusters, self.config.dim)

    def _latent(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        with threadpool_limits(limits=1):
            sf2 = self.hyperparameters.signal_variance
            return predict_nearest(self._tree, self.gps, X, sf2, self.n_jobs)
