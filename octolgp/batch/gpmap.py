"""What every GP map shares: cluster items, query validation, PLSC on the latent."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.kernels import QuadratureSet, quadrature_set
from octolgp.gp.plsc import occupancy_probability
from octolgp.partition import Cluster
from octolgp.scan import FloatArray, as_points
from octolgp.training import TrainingData


def quadrature_spacing(config: MapConfig, length_scale: float) -> float:
    """Node spacing along segments, metres: a fraction of the length scale."""
    return config.training.quadrature_spacing * length_scale


def items_and_targets(
    hits: FloatArray, seg_start: FloatArray, seg_end: FloatArray, config: MapConfig, spacing: float
) -> tuple[QuadratureSet, FloatArray]:
    """Hits and free segments as quadrature nodes, and their targets (+1 hits, −1 free).

    Parameters
    ----------
    hits : ndarray of shape (h, d)
        Hit points, metres.
    seg_start, seg_end : ndarray of shape (s, d)
        Free segments, metres.
    config : MapConfig
        Uses the quadrature node bounds of ``config.training``.
    spacing : float
        Node spacing along segments, metres.

    Returns
    -------
    items : QuadratureSet
        Hits, then free segments.
    y : ndarray of shape (h + s,)
    """
    tc = config.training
    items = quadrature_set(
        hits, seg_start, seg_end, spacing, tc.min_quadrature_nodes, tc.max_quadrature_nodes
    )
    y = np.concatenate([np.ones(hits.shape[0]), -np.ones(seg_start.shape[0])])
    return items, y


def cluster_items(
    data: TrainingData, cluster: Cluster, config: MapConfig, spacing: float
) -> tuple[QuadratureSet, FloatArray]:
    """A cluster's items and targets (:func:`items_and_targets` of its hits and pieces)."""
    return items_and_targets(
        data.hits[cluster.hits], cluster.seg_start, cluster.seg_end, config, spacing
    )


@dataclass
class GPMap(ABC):
    """A batch-built continuous map: latent GP posterior plus PLSC.

    Attributes
    ----------
    config : MapConfig
    hyperparameters : Hyperparameters
    timings : dict of str to float
        Seconds per stage of the build (``clustering``, ``fitting``, ``learning``).
    """

    config: MapConfig
    hyperparameters: Hyperparameters
    timings: dict[str, float] = field(default_factory=dict)

    def _query(self, points: object) -> FloatArray:
        """Validate query points at the boundary."""
        return as_points(points, "points", dim=self.config.dim)

    @abstractmethod
    def _latent(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Latent mean and variance at validated points."""

    def latent(self, points: object) -> tuple[FloatArray, FloatArray]:
        """GP latent mean and variance.

        Parameters
        ----------
        points : array_like of shape (q, d)
            Query points, metres, world frame.

        Returns
        -------
        mean, var : ndarray of shape (q,)
            Posterior of the latent function (variance excludes the noise).

        Raises
        ------
        OctolgpError
            On a wrong shape or a non-finite value.
        """
        return self._latent(self._query(points))

    def occupancy(self, points: object) -> FloatArray:
        """P(occupied) in [0, 1] by PLSC on the latent posterior.

        The PLSC variance is the latent variance plus the noise variance, as in the
        leave-one-out fit of α and β.

        Parameters
        ----------
        points : array_like of shape (q, d)
            Query points, metres, world frame.

        Returns
        -------
        ndarray of shape (q,)
        """
        mean, var = self.latent(points)
        hp = self.hyperparameters
        return occupancy_probability(mean, var + hp.noise_variance, hp.alpha, hp.beta)
