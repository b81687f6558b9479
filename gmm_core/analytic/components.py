"""What the 2D and 3D evidence share: the components of scan models in the world frame (Eq. 2)
with their isotropic maps (Sec. III-C), the cell that holds a component's sensor, and the cone
culling that decides which cells a component may reach."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from gmm_core.mixture import Mixture
from gmm_core.scan import ScanModel

NEGLIGIBLE_SIGMA = 7.0  # isotropic distance beyond which a component's mass (< 2.3e-11) is dropped
REACH_SIGMA = 5.0  # culling: a component reaches cells within the cone of its 5-sigma ellipse


@njit(cache=True)
def holds_sensor(sensor, center, half):
    """Whether the cell holds the sensor: -half <= s - c < half on every axis, the ray tracer's
    floor convention (a sensor on a shared boundary belongs to the upper cell), with round-off
    to spare so that neighbouring cells agree."""
    for i in range(sensor.shape[0]):
        offset = sensor[i] - center[i]
        if offset < -half * (1.0 + 1e-9) or offset >= half * (1.0 - 1e-9):
            return False
    return True


@njit(cache=True)
def may_reach(cell, rho, sensor, mean, axis, dist_mean, reach, half_angle):
    """Whether a cell (centre, bounding radius rho) may meet the rays from the sensor to the ball
    of radius `reach` around the component's mean: it must meet their box, and the cone from the
    sensor over the ball, before its far side. Cheap culling."""
    for i in range(cell.shape[0]):
        if cell[i] < min(sensor[i], mean[i] - reach) - rho or cell[i] > max(sensor[i], mean[i] + reach) + rho:
            return False
    dist_sq = 0.0
    along = 0.0
    for i in range(cell.shape[0]):
        d = cell[i] - sensor[i]
        dist_sq += d * d
        along += d * axis[i]
    dist = math.sqrt(dist_sq)
    if dist > dist_mean + reach + rho:
        return False
    if dist <= rho * (1.0 + 1e-9) or dist_mean <= reach:  # the cell may hold the sensor
        return True
    opening = half_angle + math.asin(rho / dist)
    return opening >= math.pi or along >= dist * math.cos(opening)


def isotropic_maps(covs: np.ndarray):
    """Sigma = V S V^T (ascending S), with S floored so that a singular Sigma stays usable, and the
    isotropic map S^-1/2 V^T (Sec. III-C). Returns (Sigma rebuilt from the floored S, S, V, map)."""
    evals, evecs = np.linalg.eigh(covs)
    evals = np.maximum(evals, np.maximum(evals[..., -1:] * 1e-14, 1e-300))
    covs = (evecs * evals[..., None, :]) @ np.swapaxes(evecs, -1, -2)
    isos = np.swapaxes(evecs, -1, -2) / np.sqrt(evals)[..., :, None]
    return np.ascontiguousarray(covs), evals, np.ascontiguousarray(evecs), np.ascontiguousarray(isos)


@dataclass(frozen=True)
class Components:
    """Every component of some scan models in the world frame (Eq. 2), with what culling needs."""

    means: np.ndarray  # (K, d)
    covs: np.ndarray  # (K, d, d)
    evals: np.ndarray  # (K, d) ascending
    evecs: np.ndarray  # (K, d, d) columns
    isos: np.ndarray  # (K, d, d) isotropic maps
    sensors: np.ndarray  # (K, d) sensor origin of each component's scan
    counts: np.ndarray  # (K,) N pi_k
    max_range: np.ndarray  # (K,) bool: from a free mixture
    axes: np.ndarray  # (K, d) unit sensor -> mean
    dist_means: np.ndarray  # (K,) |mean - sensor|
    reaches: np.ndarray  # (K,) REACH_SIGMA * largest sigma
    half_angles: np.ndarray  # (K,) half-angle of the cone from the sensor over the reach ball

    def cone(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.axes, self.dist_means, self.reaches, self.half_angles


@dataclass(frozen=True)
class NodeComponents:
    """A scan model's components in its node frame (both mixtures, the free one flagged), their
    covariances decomposed once: a pose turns the eigenvectors (R V) and leaves the eigenvalues, so
    world_components poses them (Eq. 2) without decomposing again. What a map server keeps per node."""

    means: np.ndarray  # (K, d)
    evals: np.ndarray  # (K, d) ascending, floored as isotropic_maps floors them
    evecs: np.ndarray  # (K, d, d) columns
    counts: np.ndarray  # (K,) N pi_k
    max_range: np.ndarray  # (K,) bool: from a free mixture
    origin: np.ndarray  # (d,) the sensor in the node frame

    @staticmethod
    def of(model: ScanModel) -> NodeComponents:
        mixtures = (model.occupied, model.free)
        _, evals, evecs, _ = isotropic_maps(np.concatenate([m.covariances for m in mixtures]))
        return NodeComponents(
            np.ascontiguousarray(np.concatenate([m.means for m in mixtures])),
            evals,
            evecs,
            np.concatenate([m.support * m.weights for m in mixtures]),
            np.concatenate([np.full(m.n_components, m is model.free) for m in mixtures]),
            np.asarray(model.origin, dtype=np.float64),
        )

    @property
    def dim(self) -> int:
        return self.origin.shape[0]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.means, self.evals, self.evecs, self.counts, self.max_range, self.origin))


def world_components(models_with_poses, dim: int) -> Components:
    """Every component of (ScanModel or NodeComponents, Pose) pairs in the world frame (Eq. 2)."""
    nodes = [(m if isinstance(m, NodeComponents) else NodeComponents.of(m), pose) for m, pose in models_with_poses]
    for node, _ in nodes:
        if node.dim != dim:
            raise ValueError(f"scan model is {node.dim}D, cells are {dim}D")
    if not nodes:  # no node: no component (the arrays below want one node to stack)
        nodes = [(NodeComponents.of(ScanModel(Mixture.empty(dim), Mixture.empty(dim), np.zeros(dim), 1.0)), None)]
    sizes = [len(node.counts) for node, _ in nodes]
    rotations = np.repeat([np.eye(dim) if p is None else p.R for _, p in nodes], sizes, axis=0)
    translations = np.repeat([np.zeros(dim) if p is None else p.t for _, p in nodes], sizes, axis=0)
    means = np.einsum("kij,kj->ki", rotations, np.concatenate([n.means for n, _ in nodes])) + translations
    sensors = np.einsum("kij,kj->ki", rotations, np.repeat([n.origin for n, _ in nodes], sizes, axis=0)) + translations
    evals = np.concatenate([n.evals for n, _ in nodes])
    evecs = rotations @ np.concatenate([n.evecs for n, _ in nodes])
    covs = (evecs * evals[:, None, :]) @ np.swapaxes(evecs, -1, -2)
    isos = np.swapaxes(evecs, -1, -2) / np.sqrt(evals)[:, :, None]
    counts = np.concatenate([n.counts for n, _ in nodes])
    max_range = np.concatenate([n.max_range for n, _ in nodes])
    dist_means = np.linalg.norm(means - sensors, axis=1)
    axes = np.ascontiguousarray((means - sensors) / np.maximum(dist_means, 1e-300)[:, None])
    reaches = REACH_SIGMA * np.sqrt(evals[:, -1])
    half_angles = np.arcsin(np.minimum(reaches / np.maximum(dist_means, 1e-300), 1.0))
    c = np.ascontiguousarray
    return Components(
        c(means), c(covs), c(evals), c(evecs), c(isos), c(sensors), c(counts), c(max_range),
        axes, dist_means, reaches, half_angles,
    )  # fmt: skip
