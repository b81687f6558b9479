"""A scan model's Monte-Carlo rays traced onto a grid as they are drawn (Algorithm 1, lines 1-9).

Each sample is drawn in the scan frame (gmm_core.sampling), moved by the scan's world pose
(Eq. 2, on the point) and traced from the moved sensor origin at once: no ray is held, so a
query's memory does not grow with the samples, and a pose change costs nothing before the trace.

A component is drawn only when its rays can reach the grid: every sample of it lies in a box
known beforehand (the normals are clipped), every ray in the box spanned by that box and the
sensor origin, and a component whose box misses the grid is skipped without drawing it. This is
exact: the counts are those of tracing every sample. A 20 x 20 x 4 m region of a 3D map skips
about half of the samples of the scans that reach it (docs/BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from gmm_core.grid import Grid
from gmm_core.pose import Pose
from gmm_core.raytrace import _trace_ray, check_cells
from gmm_core.sampling import BOX_SLACK, Z_MAX, MixtureSamples, ScanSamples, sample_normals


@njit(cache=True, inline="always")
def _moved(R, t, p, a):
    """Coordinate a of R p + t, summed in index order (the reference in the tests sums alike)."""
    s = 0.0
    for b in range(p.shape[0]):
        s += R[a, b] * p[b]
    return s + t[a]


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_mixture(
    means, chol, counts, offsets, weights, key, is_hit, R, t, origin, grid_lo, grid_hi, to_cells, dims, hits, misses
):
    """Trace every sample of one mixture (MixtureSamples' arrays), moved by (R, t), from the moved
    `origin`, with weight `weights[k]` (signed) each; grid_lo, grid_hi: the grid's box in 3D form
    (a 2D grid is one cell thick, its rays run at mid-height). Returns the samples traced."""
    d = means.shape[1]
    lo, hi = np.zeros(3), dims - 1.0  # every cell of the grid: _trace_ray's slab bounds
    cells = np.empty(dims[0] + dims[1] + dims[2] + 4, np.uint32)
    z, p, q, o = np.empty(d), np.empty(d), np.empty(3), np.empty(3)
    q[2] = o[2] = 0.5 * (grid_lo[2] + grid_hi[2])  # 2D: the mid-plane
    for a in range(d):
        o[a] = _moved(R, t, origin, a)
    traced = 0
    for k in range(counts.shape[0]):
        if counts[k] == 0:
            continue
        # The component's samples lie in mean +- half (node frame), so in centre +- |R| half in the
        # world: with the origin, a box every one of its rays stays in.
        reaches = True
        for a in range(d):
            p[a] = means[k, a]  # copied: a row view of means costs a view's making per component
        for a in range(d):
            centre, half = _moved(R, t, p, a), 0.0
            for b in range(d):
                row = 0.0
                for c in range(b + 1):
                    row += abs(chol[k, b, c])
                half += abs(R[a, b]) * (Z_MAX * row + BOX_SLACK)
            half += BOX_SLACK  # round-off of the move
            if min(centre - half, o[a]) > grid_hi[a] or max(centre + half, o[a]) < grid_lo[a]:
                reaches = False
        if not reaches:
            continue
        w = weights[k]
        for s in range(counts[k]):
            sample_normals(key, offsets[k] + s, z)
            for a in range(d):  # as sampling._place: the point in the node frame
                acc = 0.0
                for b in range(a + 1):
                    acc += chol[k, a, b] * z[b]
                p[a] = means[k, a] + acc
            for a in range(d):
                q[a] = _moved(R, t, p, a)
            _trace_ray(
                o[0], o[1], o[2], q[0], q[1], q[2], w, is_hit, grid_lo, to_cells, dims, lo, hi, 0, cells, hits, misses
            )
        traced += counts[k]
    return traced


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_blocks(
    means,
    chol,
    counts,
    offsets,
    weights,
    starts,
    keys,
    is_hit,
    node_of,
    R,
    t,
    origins,
    grid_lo,
    grid_hi,
    to_cells,
    dims,
    hits,
    misses,
):
    """_trace_mixture of every block b in order: the components starts[b]:starts[b + 1] of the
    arrays (one mixture of one node), stream keys[b], of node node_of[b] (pose R, t; sensor origin
    `origins`). One call for many nodes: a node's call from Python costs about as much as tracing
    its rays at the samples of a busy server (docs/BENCHMARKS.md). Returns the samples traced."""
    traced = 0
    for b in range(keys.shape[0]):
        lo, hi, n = starts[b], starts[b + 1], node_of[b]
        traced += _trace_mixture(
            means[lo:hi], chol[lo:hi], counts[lo:hi], offsets[lo:hi], weights[lo:hi], keys[b], is_hit[b],
            R[n], t[n], origins[n], grid_lo, grid_hi, to_cells, dims, hits, misses,
        )  # fmt: skip
    return traced


class GridCounts:
    """Float64 hit and miss counts on a grid, to which scans' rays are added (`add`)."""

    def __init__(self, grid: Grid):
        check_cells(grid)
        self.grid = grid
        d = grid.dim
        # The tracer's 3D form: a 2D grid is a 3D grid one cell thick.
        self._lo = np.append(grid.origin, 0.0) if d == 2 else grid.origin.astype(np.float64)
        self._hi = np.append(grid.upper, grid.resolution) if d == 2 else grid.upper.astype(np.float64)
        self._dims = np.array(list(grid.shape) + ([1] if d == 2 else []), dtype=np.int64)
        self.hits = np.zeros(grid.n_cells)
        self.misses = np.zeros(grid.n_cells)
        self.samples_traced = 0  # of the components that reach the grid

    def add(self, samples: ScanSamples, pose: Pose, sign: float = 1.0) -> None:
        """The rays of `samples` moved by `pose` (scan frame -> world), their weights times `sign`
        (-1 takes a scan out again: the weights are quantised, so the sums stay exact)."""
        self.add_many([(samples, pose, sign)])

    def add_many(self, scans: Sequence[tuple[ScanSamples, Pose, float]]) -> None:
        """`add` of each (samples, pose, sign) in order, in one call of the kernel: the same sums."""
        blocks = [
            (mixture, is_hit, i, sign)
            for i, (samples, _, sign) in enumerate(scans)
            for mixture, is_hit in ((samples.occupied, True), (samples.free, False))
            if mixture.counts.shape[0]
        ]
        if not blocks:
            return
        mixtures: list[MixtureSamples] = [m for m, _, _, _ in blocks]
        starts = np.zeros(len(blocks) + 1, np.int64)
        np.cumsum([m.counts.shape[0] for m in mixtures], out=starts[1:])
        self.samples_traced += _trace_blocks(
            np.concatenate([m.means for m in mixtures]),
            np.concatenate([m.chol for m in mixtures]),
            np.concatenate([m.counts for m in mixtures]),
            np.concatenate([m.offsets for m in mixtures]),
            np.concatenate([m.weights if sign == 1.0 else sign * m.weights for m, _, _, sign in blocks]),
            starts,
            np.array([m.key for m in mixtures], np.uint64),
            np.array([is_hit for _, is_hit, _, _ in blocks]),
            np.array([i for _, _, i, _ in blocks], np.int64),
            np.stack([pose.R for _, pose, _ in scans]).astype(np.float64),
            np.stack([pose.t for _, pose, _ in scans]).astype(np.float64),
            np.stack([samples.origin for samples, _, _ in scans]).astype(np.float64),
            self._lo, self._hi, 1.0 / self.grid.resolution, self._dims, self.hits, self.misses,
        )  # fmt: skip

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(hits, misses) shaped as the grid's arrays."""
        return self.hits.reshape(self.grid.array_shape), self.misses.reshape(self.grid.array_shape)
