"""Monte-Carlo counts of a 3D grid smoothed across neighbouring cells before Eq. 11.

The hit and miss counts of a Monte-Carlo reconstruction (Eq. 10) estimate the expected counts with
a noise that falls as 1 / sqrt(samples per cell). Before the MAP estimate, 3D counts are smoothed
by the separable kernel [c, 1 - 2c, c] along each axis, with c = SMOOTHING_AT_ONE / sqrt(samples per
cell), at most MAX_SMOOTHING: a little resolution traded for variance, less of it the more samples.
Measured (docs/BENCHMARKS.md, thirtieth session), AUROC unsmoothed -> smoothed at 1 / 4 samples per
cell: BALM OS0 at 0.2 m against the raw grid 0.9921 -> 0.9952 / 0.9963 -> 0.9966; the mine map's 3D
region against the world 0.9926 -> 0.9967 / 0.9949 -> 0.9970 (over its best-seen cells 0.9961 ->
0.9964 / 0.9973 -> 0.9972: where samples are plenty the kernel costs a little). 0.35 samples per
cell smoothed are about as good as 1 unsmoothed, for a third of the rays.

2D grids are not smoothed: on the Intel log at the default 4 samples per cell, c = 0.05 lowered AUROC
against the raw grid by 0.0003-0.0024 (0.05 and 0.1 m; at 1 sample per cell it raised it by up to
0.0036), so 2D maps keep the paper's estimate.

A cell beyond the grid's edge is taken as the nearest cell inside (a constant field stays
constant): the edge cells of a window may differ from the same cells of a larger grid by c times
their difference to the neighbour outside.
"""

from __future__ import annotations

import numpy as np
from numba import njit

SMOOTHING_AT_ONE = 0.075  # c at one sample per cell: the best of 0.03-0.25 on BALM and the mine map
MAX_SMOOTHING = 0.125  # c at fewer than 0.36 samples per cell: beyond 0.15 every map measured lost


def smoothing_weight(samples_per_cell: float, dim: int) -> float:
    """c of the kernel [c, 1 - 2c, c] for counts of `samples_per_cell` on a `dim`-D grid (0: none)."""
    if dim != 3:
        return 0.0
    return min(MAX_SMOOTHING, SMOOTHING_AT_ONE / float(np.sqrt(samples_per_cell)))


def smoothed(counts: np.ndarray, weight: float) -> np.ndarray:
    """float64 `counts` convolved with [weight, 1 - 2 weight, weight] along each axis (edges held);
    `counts` itself (as float64) for weight 0. A new array: the input is not changed."""
    if not 0.0 <= weight <= 1.0 / 3.0:
        raise ValueError(f"weight: the kernel [c, 1 - 2c, c] needs 0 <= c <= 1/3, got {weight}")
    counts = np.asarray(counts, dtype=np.float64)
    if weight == 0.0 or counts.size == 0:
        return counts
    out = np.ascontiguousarray(counts).copy()
    scratch = np.empty_like(out)
    shape = out.shape
    for axis in range(out.ndim):
        # The array as (before, along, after): the axis to smooth in the middle, C order kept.
        before, after = int(np.prod(shape[:axis])), int(np.prod(shape[axis + 1 :]))
        view = (before, shape[axis], after)
        if after == 1:  # the last axis: its own loop, which vectorises along the axis
            _smooth_rows(out.reshape(view[:2]), scratch.reshape(view[:2]), weight)
        else:
            _smooth_axis(out.reshape(view), scratch.reshape(view), weight)
        out, scratch = scratch, out
    return out


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
