"""OM_MGP: a mixture of GP experts (Kim & Kim Table II baseline).

Each expert is a GP on one disjoint cluster and predicts every query point; a
gating function over the clusters weighs them: ``g_k(x) ∝ n_k N(x; c_k, Σ_k)`` with
the cluster's hit mean and covariance (regularised by ``(box_size / 4)²``). The
mixture's moments are ``μ = Σ g_k μ_k`` and ``σ² = Σ g_k (σ_k² + μ_k²) − μ²``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from octolgp.batch.gpmap import GPMap
from octolgp.gp.regression import LocalGP, predict_latent
from octolgp.partition import Cluster
from octolgp.scan import FloatArray
from octolgp.training import TrainingData


@dataclass(frozen=True)
class Gate:
    """Gaussian gating parameters, one row per expert."""

    means: FloatArray  # (K, d)
    precisions: FloatArray  # (K, d, d)
    log_norm: FloatArray  # (K,) log n_k − ½ log det Σ_k


def make_gate(data: TrainingData, clusters: list[Cluster], box_size: float) -> Gate:
    """Fit the gating Gaussians to each cluster's hits."""
    d = data.dim
    reg = (box_size / 4.0) ** 2 * np.eye(d)
    means, precs, norms = [], [], []
    for c in clusters:  # one iteration per expert
        pts = data.hits[c.hits]
        cov = np.cov(pts.T).reshape(d, d) if pts.shape[0] > 1 else np.zeros((d, d))
        cov = cov + reg
        means.append(pts.mean(axis=0))
        precs.append(np.linalg.inv(cov))
        norms.append(np.log(c.n_own) - 0.5 * np.linalg.slogdet(cov)[1])
    return Gate(np.array(means), np.array(precs), np.array(norms))


def gate_weights(gate: Gate, X: FloatArray) -> FloatArray:
    """Gating weights of shape (q, K), rows summing to 1."""
    diff = X[:, None, :] - gate.means[None, :, :]
    maha = np.einsum("qki,kij,qkj->qk", diff, gate.precisions, diff)
    logw = gate.log_norm[None, :] - 0.5 * maha
    return np.asarray(np.exp(logw - logsumexp(logw, axis=1, keepdims=True)))


@dataclass
class MixtureGPMap(GPMap):
    """Mixture of GP experts merged by a Gaussian gating function."""

    gps: list[LocalGP] = field(default_factory=list)
    gate: Gate | None = None

    def _latent(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        assert self.gate is not None, "MixtureGPMap built without a gate"
        w = gate_weights(self.gate, X)
        mean = np.zeros(X.shape[0])
        second = np.zeros(X.shape[0])
        for k, gp in enumerate(self.gps):  # every expert predicts everywhere
            m, v = predict_latent(gp, X)
            mean += w[:, k] * m
            second += w[:, k] * (v + m * m)
        return mean, np.maximum(second - mean * mean, 0.0)
