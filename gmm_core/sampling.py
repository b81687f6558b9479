"""Deterministic Monte-Carlo samples of a scan's mixtures (Sec. III-C3, Algorithm 1 line 1).

Each component k gets n_k samples, enough to put a few in every cell it covers at the query
resolution, and each sample carries the weight N pi_k / n_k. Summed along rays, the weights
estimate the expected number of beams (Eq. 10) whatever n_k is: more samples only lower the
Monte-Carlo variance, so maps at different resolutions agree in their counts.
"""

from __future__ import annotations

import hashlib

import numpy as np
from numba import njit

from gmm_core.mixture import Mixture
from gmm_core.scan import ScanModel

MAX_SAMPLES_PER_COMPONENT = 4096
# Weights are rounded to multiples of 2^-26 (relative change below 1e-5 for weights over 0.003):
# sums of them are then exact in float64 up to 2^27 beams in a cell, so counts do not depend on
# the order scans are added in, and a map server can add and subtract scans on a cached tile
# and still get the bytes of a fresh reconstruction.
WEIGHT_QUANTUM = 2.0**-26


def samples_per_component(mixture: Mixture, resolution: float, samples_per_cell: float) -> np.ndarray:
    """n_k = ceil(samples_per_cell * max(N pi_k, cells covered by the 2-sigma box of k))."""
    if mixture.n_components == 0:
        return np.zeros(0, dtype=np.int64)
    sigmas = np.sqrt(np.clip(np.linalg.eigvalsh(mixture.covariances), 0.0, None))
    cells = np.prod(np.maximum(1.0, 4.0 * sigmas / resolution), axis=1)
    expected_points = mixture.support * mixture.weights
    n = np.ceil(samples_per_cell * np.maximum(expected_points, cells))
    return np.clip(n, 1, MAX_SAMPLES_PER_COMPONENT).astype(np.int64)


def sample_mixture(mixture: Mixture, counts: np.ndarray, rng: np.random.Generator):
    """`counts[k]` samples of each component and their weights N pi_k / counts[k]."""
    chol = np.linalg.cholesky(mixture.covariances)
    z = rng.standard_normal((int(counts.sum()), mixture.dim))
    weights = np.round(mixture.support * mixture.weights / np.maximum(counts, 1) / WEIGHT_QUANTUM) * WEIGHT_QUANTUM
    return _place(mixture.means, chol, counts, weights, z)


@njit(cache=True, nogil=True)
def _place(means, chol, counts, weights, z):
    """Sample i of component k at means[k] + chol[k] z[i], with weight weights[k]; outside the
    GIL, so a map server's tracer threads draw samples in parallel."""
    n, d = z.shape
    points = np.empty((n, d))
    sample_weights = np.empty(n)
    i = 0
    for k in range(counts.shape[0]):
        for _ in range(counts[k]):
            for a in range(d):
                s = 0.0
                for b in range(a + 1):  # lower triangular
                    s += chol[k, a, b] * z[i, b]
                points[i, a] = means[k, a] + s
            sample_weights[i] = weights[k]
            i += 1
    return points, sample_weights


def scan_rays(model: ScanModel, resolution: float, seed: int, samples_per_cell: float = 1.0):
    """Ray end points in the scan frame, their weights, and whether each ends in a hit.

    Samples of the occupied mixture end in a hit; samples of the free mixture (no-return
    beams) only add misses. The same (model, resolution, seed) always gives the same rays.
    """
    rng = np.random.default_rng([seed, int(round(resolution * 1e6))])
    occ_points, occ_w = sample_mixture(
        model.occupied, samples_per_component(model.occupied, resolution, samples_per_cell), rng
    )
    free_points, free_w = sample_mixture(
        model.free, samples_per_component(model.free, resolution, samples_per_cell), rng
    )
    ends = np.concatenate([occ_points, free_points])
    weights = np.concatenate([occ_w, free_w])
    is_hit = np.concatenate([np.ones(len(occ_w), bool), np.zeros(len(free_w), bool)])
    return ends, weights, is_hit


def scan_seed(*keys) -> int:
    """A stable 63-bit seed from identifiers such as (robot, node) or (run seed, scan index).

    Stable across processes and Python versions (no `hash()`), so a restarted server draws
    the same samples.
    """
    digest = hashlib.blake2b(repr(keys).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1
