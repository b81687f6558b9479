"""Gaussian mixtures (Eq. 1) with their support size, and their rigid transform (Eq. 2)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gmm_core.pose import Pose


@dataclass(frozen=True)
class Mixture:
    """G = sum_j pi_j N(x | mu_j, Sigma_j), Eq. 1, fitted to `support` points.

    The support size N turns the density into evidence: N * pi_j is the expected number of
    points of component j (Eq. 10).
    """

    weights: np.ndarray  # (K,) pi_j, sum to 1 (empty mixture: K = 0)
    means: np.ndarray  # (K, d)
    covariances: np.ndarray  # (K, d, d), symmetric positive definite
    support: int  # N, number of points the mixture was fitted to

    def __post_init__(self):
        weights = np.ascontiguousarray(self.weights, dtype=np.float64).reshape(-1)
        means = np.ascontiguousarray(self.means, dtype=np.float64)
        covs = np.ascontiguousarray(self.covariances, dtype=np.float64)
        k = weights.shape[0]
        if means.ndim != 2 or means.shape[0] != k or means.shape[1] not in (2, 3):
            raise ValueError(f"mixture: means must be (K, 2|3) with K={k}, got {means.shape}")
        d = means.shape[1]
        if covs.shape != (k, d, d):
            raise ValueError(f"mixture: covariances must be {(k, d, d)}, got {covs.shape}")
        if int(self.support) < 0:
            raise ValueError(f"mixture: support must be >= 0, got {self.support}")
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "covariances", covs)
        object.__setattr__(self, "support", int(self.support))

    @staticmethod
    def empty(dim: int) -> Mixture:
        return Mixture(np.zeros(0), np.zeros((0, dim)), np.zeros((0, dim, dim)), 0)

    @property
    def dim(self) -> int:
        return self.means.shape[1]

    @property
    def n_components(self) -> int:
        return self.weights.shape[0]

    def transformed(self, pose: Pose) -> Mixture:
        """The same mixture seen from the parent frame: mu' = R mu + t, Sigma' = R Sigma R^T (Eq. 2)."""
        R = pose.R
        means = self.means @ R.T + pose.t
        covs = np.einsum("ij,kjl,ml->kim", R, self.covariances, R)
        return Mixture(self.weights, means, covs, self.support)

    def log_density(self, points: np.ndarray) -> np.ndarray:
        """log p(x) for (n, d) points; the plain-numpy reference used in tests and fit checks."""
        points = np.asarray(points, dtype=np.float64)
        d = self.dim
        chol = np.linalg.cholesky(self.covariances)  # (K, d, d)
        diff = points[None, :, :] - self.means[:, None, :]  # (K, n, d)
        sol = np.linalg.solve(chol[:, None, :, :], diff[..., None])[..., 0]
        maha = np.sum(sol**2, axis=-1)  # (K, n)
        log_det = 2 * np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)
        log_comp = np.log(self.weights)[:, None] - 0.5 * (maha + log_det[:, None] + d * np.log(2 * np.pi))
        top = log_comp.max(axis=0)
        return top + np.log(np.exp(log_comp - top).sum(axis=0))

    def bounds(self, n_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box holding every component's n-sigma ellipsoid (lo, hi)."""
        if self.n_components == 0:
            return np.full(self.dim, np.inf), np.full(self.dim, -np.inf)
        half = n_sigma * np.sqrt(np.diagonal(self.covariances, axis1=1, axis2=2))
        return (self.means - half).min(axis=0), (self.means + half).max(axis=0)
