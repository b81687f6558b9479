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
constant): the edge cells of a window may differ from the same cells of a larger grid.
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


def smoothed(counts: np.ndarray, weight: float) -> np.ndarray:
    """float64 `counts` convolved with [weight, 1 - 2 weight, weight] along each axis (edges held);
    `counts` itself (as float64) for weight 0. A new array: the input is not changed."""
    if not 0.0 <= weight <= 1.0 / 3.0:
        raise ValueError(f"weight: the kernel [c, 1 - 2c, c] needs 0 <= c <= 1/3, got {weight}")
    counts = np.ascontiguousarray(counts, dtype=np.float64)
    if weight == 0.0 or counts.size == 0:
        return counts
    src, shape = counts, counts.shape
    buffers = np.empty_like(counts), np.empty_like(counts)  # the passes alternate between them
    for axis in range(counts.ndim):
        dst = buffers[axis % 2]
        # The array as (before, along, after): the axis to smooth in the middle, C order kept.
        before, after = int(np.prod(shape[:axis])), int(np.prod(shape[axis + 1 :]))
        view = (before, shape[axis], after)
        if after == 1:  # the last axis: its own loop, which vectorises along the axis
            _smooth_rows(src.reshape(view[:2]), dst.reshape(view[:2]), weight)
        else:
            _smooth_axis(src.reshape(view), dst.reshape(view), weight)
        src = dst
    return src


@njit(cache=True, nogil=True)
def _smooth_axis(src, dst, c):
    """dst[i, j, k] = (1 - 2c) src[i, j, k] + c (src[i, j - 1, k] + src[i, j + 1, k]), j clamped."""
    keep = 1.0 - 2.0 * c
    n_i, n_j, n_k = src.shape
    for i in range(n_i):
        for j in range(n_j):
            left, right = max(j - 1, 0), min(j + 1, n_j - 1)
            for k in range(n_k):
                dst[i, j, k] = keep * src[i, j, k] + c * (src[i, left, k] + src[i, right, k])


@njit(cache=True, nogil=True)
def _smooth_rows(src, dst, c):
    """_smooth_axis along the rows of a 2D array: the edge cells apart, the rest in one loop."""
    keep = 1.0 - 2.0 * c
    n_i, n_j = src.shape
    last = n_j - 1
    for i in range(n_i):
        dst[i, 0] = keep * src[i, 0] + c * (src[i, 0] + src[i, min(1, last)])
        for j in range(1, last):
            dst[i, j] = keep * src[i, j] + c * (src[i, j - 1] + src[i, j + 1])
        if last > 0:
            dst[i, last] = keep * src[i, last] + c * (src[i, last - 1] + src[i, last])
