"""OM_GP: one global GP on all training data (Kim & Kim Table II baseline)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolgp.batch.gpmap import GPMap
from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.quadrature import cluster_items, quadrature_spacing
from octolgp.gp.regression import LocalGP, fit_local_gp, predict_latent
from octolgp.partition import Cluster
from octolgp.scan import FloatArray
from octolgp.training import TrainingData


def whole_data_cluster(data: TrainingData) -> Cluster:
    """A single cluster holding every training item, segments whole.

    With no items (every beam on its sensor) the cluster is empty, at the origin, and
    the GP fitted on it predicts the prior.
    """
    every = np.concatenate([data.hits, data.seg_start, data.seg_end])
    if every.shape[0] == 0:
        lo = hi = np.zeros(every.shape[1])
    else:
        lo, hi = every.min(axis=0), every.max(axis=0)
    return Cluster(
        centre=(lo + hi) / 2.0,
        lo=lo,
        hi=hi,
        hits=np.arange(data.hits.shape[0], dtype=np.int64),
        seg_start=data.seg_start,
        seg_end=data.seg_end,
        n_own=data.n_items,
    )


def fit_global_gp(data: TrainingData, config: MapConfig, hp: Hyperparameters) -> LocalGP:
    """Fit one GP on all items: ``O(n³)`` in the number of items."""
    items, y = cluster_items(
        data, whole_data_cluster(data), config, quadrature_spacing(config, hp.length_scale)
    )
    return fit_local_gp(items, y, hp)


@dataclass
class GlobalGPMap(GPMap):
    """A single GP over the whole map."""

    gp: LocalGP | None = None

    def _latent(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        assert self.gp is not None, "GlobalGPMap built without a GP"
        return predict_latent(self.gp, X)
