"""From evidence counts to occupancy: the MAP estimate (Eq. 11) and the variance dead band (Eq. 12)."""

from __future__ import annotations

import numpy as np
from numba import njit

from gmm_core.smoothing import neighbourhood_estimate, prior_beams

DEFAULT_PRIOR = 0.2  # N_p: measured on Intel (docs/BENCHMARKS.md), better than 1 for sparse data

OCCUPIED, FREE, UNKNOWN = 1, 0, -1
# sigma^2 of Eq. 12 for maps shown to people: thresholds 0.3 and 0.7. The paper's Fig. 8 uses 0.06
# (0.064 / 0.936), which on the Intel replay at 10 cm classifies 6.5 % of the raw grid's occupied
# cells as occupied (walls are grazed by many beams, so their p is moderate: median 0.72); 0.21
# classifies 57 % of them with 92 % precision, and free cells at 96 % precision and recall.
DEFAULT_VARIANCE = 0.21


def map_estimate(hits: np.ndarray, misses: np.ndarray, prior: float = DEFAULT_PRIOR) -> np.ndarray:
    """theta_MAP = (N_H + N_p) / (N_H + N_M + 2 N_p), Eq. 11, in float32; 0.5 where nothing was seen.

    Counts of any float type are read as float32, one cell at a time: a server estimates every tile
    it updates, and numpy's casts and temporaries cost 11 times as much (518 against 45 us for a
    256 x 256 tile of float64 counts, Intel Xeon)."""
    hits, misses = _checked(hits, misses, prior)
    out = np.empty(hits.shape, np.float32)
    h, m = (
        a.reshape(-1) if a.dtype in (np.float32, np.float64) else a.reshape(-1).astype(np.float32)
        for a in (hits, misses)
    )
    _map_estimate(h, m, np.float32(prior), np.float32(2 * prior), out.reshape(-1))
    return out


def monte_carlo_estimate(
    hits: np.ndarray, misses: np.ndarray, samples_per_cell: float, prior: float = DEFAULT_PRIOR
) -> np.ndarray:
    """Eq. 11 of Monte-Carlo counts drawn at `samples_per_cell`, in float32: on a 3D grid with the
    prior taken from each cell's neighbourhood (gmm_core.smoothing), as wherever a 3D map is served
    or replayed; map_estimate in 2D."""
    n0 = prior_beams(samples_per_cell, np.ndim(hits))
    if n0 == 0.0:
        return map_estimate(hits, misses, prior)
    hits, misses = _checked(hits, misses, prior)
    return neighbourhood_estimate(hits, misses, n0, prior)


def _checked(hits, misses, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """(hits, misses) as arrays, or a ValueError naming the field that is wrong."""
    if prior <= 0:
        raise ValueError(f"prior: N_p must be positive, got {prior}")
    hits, misses = np.asarray(hits), np.asarray(misses)
    if hits.shape != misses.shape:
        raise ValueError(f"misses: shape {misses.shape} differs from the hits' {hits.shape}")
    return hits, misses


@njit(cache=True, nogil=True, error_model="numpy")
def _map_estimate(hits, misses, prior, two_prior, out):
    """Eq. 11 cell by cell in float32, the operations of numpy's (h + p) / (h + m + 2 p) on float32 arrays."""
    for i in range(out.shape[0]):
        h = np.float32(hits[i])
        out[i] = (h + prior) / (h + np.float32(misses[i]) + two_prior)


MIN_VARIANCE, MAX_VARIANCE = 0.0, 0.25  # sigma^2 = p (1 - p) of Eq. 12 lies in [0, 1/4]


def check_variance(variance: float, field: str = "variance") -> float:
    """`variance` if it is a sigma^2 of Eq. 12, in [MIN_VARIANCE, MAX_VARIANCE]; else a ValueError naming `field`."""
    if not MIN_VARIANCE <= variance <= MAX_VARIANCE:
        raise ValueError(f"{field}: sigma^2 must lie in [{MIN_VARIANCE:g}, {MAX_VARIANCE:g}], got {variance}")
    return variance


def class_bounds(variance: float) -> tuple[np.float64, np.float64]:
    """(free_max, occupied_min) = (1 -+ sqrt(1 - 4 sigma^2)) / 2 of Eq. 12: a cell is FREE for p <=
    free_max and p < 0.5, OCCUPIED for p >= occupied_min and p > 0.5. Float64 scalars, so float32
    probabilities are compared in double precision."""
    check_variance(variance)
    half_band = 0.5 * np.sqrt(np.float64(1.0 - 4.0 * variance))
    return 0.5 - half_band, 0.5 + half_band


def classify(prob: np.ndarray, variance: float) -> np.ndarray:
    """OCCUPIED / FREE / UNKNOWN by the thresholds (1 ± sqrt(1 - 4 sigma^2)) / 2 of Eq. 12.

    A cell whose Bernoulli variance p(1 - p) exceeds `variance` stays UNKNOWN, and so does
    p = 0.5, the prior, whatever the band.
    """
    free_max, occupied_min = class_bounds(variance)
    out = np.full(np.shape(prob), UNKNOWN, dtype=np.int8)
    out[(prob >= occupied_min) & (prob > 0.5)] = OCCUPIED
    out[(prob <= free_max) & (prob < 0.5)] = FREE
    return out
