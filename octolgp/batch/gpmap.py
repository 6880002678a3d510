"""What every batch GP map shares: query validation and PLSC on the latent posterior."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.plsc import latent_occupancy
from octolgp.scan import FloatArray, as_points


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
        return latent_occupancy(mean, var, hp)
