"""The prior of Eq. 11 for Monte-Carlo counts of a 3D grid, taken from each cell's neighbourhood.

The hit and miss counts of a Monte-Carlo reconstruction (Eq. 10) carry a noise whose variance falls
as 1 / (samples per cell). Eq. 11's Beta prior (N_p beams each way, p = 0.5) is the same for every
cell; for 3D counts it is taken from the cell's neighbourhood instead (empirical Bayes): the counts
smoothed by the separable kernel [c, 1 - 2c, c] along each axis (c = NEIGHBOURHOOD_WEIGHT) give an
estimate p_nb by Eq. 11, which enters as a prior worth N_0 beams,

    theta = (N_H + N_0 p_nb + N_p) / (N_H + N_M + N_0 + 2 N_p),    N_0 = PRIOR_BEAMS_AT_ONE / samples per cell,

so a cell seen by few rays takes most of its estimate from around it and a well-seen cell keeps its
own; the prior weighs as much as the noise it stands in for. Measured (docs/BENCHMARKS.md, thirtieth
session), AUROC of Eq. 11 as printed -> with this prior, at 1 / 4 samples per cell: BALM OS0 at 0.2 m
against the raw grid 0.9921 -> 0.9956 / 0.9963 -> 0.9968; the mine map's 3D region against the world
0.9926 -> 0.9972 / 0.9949 -> 0.9974, over its best-seen cells 0.9961 -> 0.9970 / 0.9973 -> 0.9974;
0.3 samples per cell with it are about as good as 1 without. It is not better everywhere: the mine
sim's whole graded map 0.9931 -> 0.9923, BALM with 10 % of its points 0.9602 -> 0.9579 (Kurt3D and
the OctoMap scan at 10 % gained 0.015 and 0.012). With N_0 / sqrt(samples per cell) instead, the
prior cost more at 4 (0.9918, 0.9561); smoothing the counts themselves, without the cell's own
term, gained less and lost on the best-seen cells.

2D grids keep Eq. 11 as printed: on the Intel log at the default 4 samples per cell, smoothed counts
(c = 0.05) lowered AUROC against the raw grid by 0.0003-0.0024 (0.05 and 0.1 m).

A cell beyond the grid's edge is taken as the nearest cell inside (a constant field stays
constant): the edge cells of a window may differ from the same cells of a larger grid. On the mine
region (200 x 200 x 40 cells) a halo of one cell would change 12-16 k of its 110 k edge cells, by up
to 0.17 at 0.3 samples per cell, and its AUROC not in the fifth decimal: no halo is traced.
"""

from __future__ import annotations

import numpy as np
from numba import njit

NEIGHBOURHOOD_WEIGHT = 0.125  # c of the kernel that makes p_nb; 0.25 gained at few samples, lost at 4
PRIOR_BEAMS_AT_ONE = 16.0  # N_0 at one sample per cell; 8-64 tried at 0.25-4 samples per cell


def prior_beams(samples_per_cell: float, dim: int) -> float:
    """N_0, the beams the neighbourhood's estimate is worth, for counts of `samples_per_cell` on a
    `dim`-D grid (0: none)."""
    if dim != 3:
        return 0.0
    return PRIOR_BEAMS_AT_ONE / float(samples_per_cell)


def neighbourhood_estimate(hits: np.ndarray, misses: np.ndarray, n0: float, prior: float) -> np.ndarray:
    """theta = (N_H + N_0 p_nb + N_p) / (N_H + N_M + N_0 + 2 N_p) of each cell of 3D counts
    (z, y, x), p_nb Eq. 11 of the counts smoothed with c = NEIGHBOURHOOD_WEIGHT; float32."""
    if hits.ndim != 3 or misses.shape != hits.shape:
        raise ValueError(f"hits, misses: 3D counts of one shape expected, got {hits.shape} and {misses.shape}")
    out = np.empty(hits.shape, np.float32)
    hits, misses = (np.ascontiguousarray(a, dtype=np.float64) for a in (hits, misses))
    _estimate(hits, misses, NEIGHBOURHOOD_WEIGHT, float(n0), float(prior), out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _estimate(hits, misses, c, n0, prior, out):
    """neighbourhood_estimate in one pass over z: each slab blurred along x and y once, three of them
    held (z - 1, z, z + 1), the blur along z and the estimate taken cell by cell. Blurring the whole
    grid axis by axis wrote four grids of float64 (each freshly faulted in) and read them back: 55 ms
    for the 1.6 M cells of the mine region, against the counts read once here (docs/BENCHMARKS.md,
    thirty-first session)."""
    n_z, n_y, n_x = hits.shape
    keep = 1.0 - 2.0 * c
    held = np.empty((3, 2, n_y, n_x))  # slab z at z % 3: its hits and misses blurred along x and y
    along_x = np.empty((n_y, n_x))
    for z in range(min(2, n_z)):
        _blur_xy(hits[z], misses[z], c, along_x, held[z % 3])
    for z in range(n_z):
        if 2 <= z + 1 < n_z:  # slab z + 1 takes the place of slab z - 2
            _blur_xy(hits[z + 1], misses[z + 1], c, along_x, held[(z + 1) % 3])
        below, here, above = held[max(z - 1, 0) % 3], held[z % 3], held[min(z + 1, n_z - 1) % 3]
        for y in range(n_y):
            for x in range(n_x):
                h_nb = keep * here[0, y, x] + c * (below[0, y, x] + above[0, y, x])
                m_nb = keep * here[1, y, x] + c * (below[1, y, x] + above[1, y, x])
                seen_nb = h_nb + m_nb + 2.0 * prior  # p_nb = (h_nb + prior) / seen_nb, one division a cell
                h, m = hits[z, y, x], misses[z, y, x]
                out[z, y, x] = ((h + prior) * seen_nb + n0 * (h_nb + prior)) / ((h + m + n0 + 2.0 * prior) * seen_nb)


@njit(cache=True, nogil=True, inline="always")
def _blur_xy(hits, misses, c, along_x, out):
    """Slabs (y, x) of hits and misses blurred by [c, 1 - 2c, c] along x, then y (a cell beyond an
    edge is the edge cell: a constant field stays constant), into out[0] and out[1]."""
    n_y, n_x = hits.shape
    keep = 1.0 - 2.0 * c
    for q in range(2):
        slab = hits if q == 0 else misses
        last = n_x - 1
        for y in range(n_y):  # the edge cells apart: the loop between them vectorises
            along_x[y, 0] = keep * slab[y, 0] + c * (slab[y, 0] + slab[y, min(1, last)])
            for x in range(1, last):
                along_x[y, x] = keep * slab[y, x] + c * (slab[y, x - 1] + slab[y, x + 1])
            if last > 0:
                along_x[y, last] = keep * slab[y, last] + c * (slab[y, last - 1] + slab[y, last])
        for y in range(n_y):
            before, after = max(y - 1, 0), min(y + 1, n_y - 1)
            for x in range(n_x):
                out[q, y, x] = keep * along_x[y, x] + c * (along_x[before, x] + along_x[after, x])
