"""A scan model's Monte-Carlo rays traced onto a grid as they are drawn (Algorithm 1, lines 1-9).

Each sample is drawn in the scan frame (gmm_core.sampling), moved by the scan's world pose
(Eq. 2, on the point) and traced from the moved sensor origin at once: no ray is held, so a
query's memory does not grow with the samples, and a pose change costs nothing before the trace.

In 3D the misses are thinned toward the sensor. A component's n rays make a cone from the sensor
whose section at ray parameter t is t^2 times the component's, so near the sensor every ray crosses
the same few cells, far more rays a cell than the samples per cell asked for at the component. On
t in [2^-(l+1), 2^-l) (level l) only the first m_l = ceil(n / 4^l) samples carry misses, each with
weight n / m_l times its own: at least as many rays a cell of the section as at the component. A
cell takes the weight of the level at which the ray enters it. Each sample's marginal is the
component's, so the expected counts are unchanged (the estimate stays unbiased), every hit is
traced, and a 3D region of the mine map crosses 1.8x fewer cells (docs/BENCHMARKS.md). A sample's
ray is traced as one segment per level it takes part in (sample 0 in every level, to the sensor).
2D rays are traced whole: a section grows only as t there, and thinning gained 1.15x on a tile.
Thinning further by the distance from the sample (half the samples per doubling beyond 1 m) crossed
2.7x fewer cells of the mine region but lost as much AUROC as fewer samples per cell do, for 1.1x
(docs/BENCHMARKS.md, twenty-eighth session): the misses far from a sample are not spare.

An occupied sample's misses stop HIT_STOP_CELLS cells short of it (its hit stays in its own cell).
A sample's depth along its ray scatters by its component's thickness that way, and the rays to the
samples behind a surface crossed the cells of the surface in front of them: a wall seen at a slant,
or the ground at range, was carved free by its own samples (the synthetic street's walls at
20-40 m: 15.8 % of their cells called free, where OctoMap called 2.8 %). One cell short, AUROC
against the raw grid of BALM with 30 / 10 % of its points 0.9860 -> 0.9890 / 0.9579 -> 0.9694, the
occupied cells it calls free 4.4 -> 2.9 % / 6.2 -> 4.4 %; with every point 0.9967 -> 0.9962
(docs/BENCHMARKS.md, thirty-fourth session); on the Intel lab in 2D every row of the AUROC table
rose, by 0.0001-0.0099 (thirty-fifth session). Where a component is thick against the cells (a 1 cm
grid, a component fitted to few points), one cell is not its depth: the stop is then HIT_STOP_SIGMAS
of its thinnest standard deviation (hit_stop), and the Intel lab at 1 cm with every beam rose 0.9760 ->
0.9860, at 10 cm with a tenth of them 0.9257 -> 0.9477 (thirty-fifth session). The free mixture's
rays run to their ends.

A component is drawn only when its rays can reach the grid: every sample of it lies in a box
known beforehand (the normals are clipped), every ray in the box spanned by that box and the
sensor origin, and a component whose box misses the grid is skipped without drawing it. This is
exact: the counts are those of tracing every sample (thinned alike). A 20 x 20 x 4 m region of a
3D map skips about half of the samples of the scans that reach it (docs/BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from gmm_core.grid import Grid
from gmm_core.pose import Pose
from gmm_core.raytrace import _trace_ray, check_cells
from gmm_core.sampling import BOX_SLACK, WEIGHT_QUANTUM, Z_MAX, MixtureSamples, ScanSamples, sample_normals

# A sample of the occupied mixture claims free only the cells its ray crosses until this many cells
# (of the grid traced) short of it (module docstring); 1.5 and 2 lost AUROC with every point, in 3D and 2D.
HIT_STOP_CELLS = 1.0
# ... or this many of its component's thinnest standard deviations, where that is farther: the ray to
# a sample on the component's mid-plane stops at the near face of its 3-sigma slab. 4 and 6 lost
# AUROC against the mine sim's world (0.9917 -> 0.9908 / 0.9884), which 3 left as it was.
HIT_STOP_SIGMAS = 3.0


@njit(cache=True, inline="always")
def hit_stop(cell_size, thickness):
    """How far short of an occupied sample its misses stop (m), on a grid of cells `cell_size` (m),
    the sample's component `thickness` (its thinnest principal standard deviation, m) thick."""
    return max(HIT_STOP_CELLS * cell_size, HIT_STOP_SIGMAS * thickness)


@njit(cache=True, inline="always")
def _moved(R, t, p, a):
    """Coordinate a of R p + t, summed in index order (the reference in the tests sums alike)."""
    s = 0.0
    for b in range(p.shape[0]):
        s += R[a, b] * p[b]
    return s + t[a]


@njit(cache=True, inline="always")
def _at(o, q, t, a):
    """Coordinate a of the point at parameter t of the ray o -> q (q itself at t = 1)."""
    return q[a] if t == 1.0 else o[a] + t * (q[a] - o[a])


@njit(cache=True, inline="always", error_model="numpy")
def _trace_thinned(o, q, w, s, n, grid_lo, to_cells, dims, lo, hi, cells, hits, misses):
    """The misses of sample s of a component of n samples, traced o -> q (every cell it crosses, q's
    too) in one segment per level it takes part in (module docstring), from q inward; each segment
    but the innermost leaves out the cell it starts in, which the ray entered on the level inside."""
    b, m = 1.0, n  # the level's outer end and its samples
    while True:
        inner = (m + 3) // 4  # samples on the next level in: ceil(n / 4^(l+1))
        a = 0.5 * b if inner < m else 0.0  # one sample left: it carries the misses to the sensor
        weight = np.rint(w * n / m / WEIGHT_QUANTUM) * WEIGHT_QUANTUM
        _trace_ray(
            _at(o, q, a, 0), _at(o, q, a, 1), _at(o, q, a, 2), _at(o, q, b, 0), _at(o, q, b, 1), _at(o, q, b, 2),
            weight, False, a > 0.0, grid_lo, to_cells, dims, lo, hi, 0, cells, hits, misses,
        )  # fmt: skip
        if a == 0.0 or s >= inner:
            return
        b, m = a, inner


@njit(cache=True, inline="always")
def _cell_of(q, grid_lo, to_cells, dims):
    """The flat number (z ny + y) nx + x of the cell holding the 3D point q, -1 outside the grid."""
    flat = 0
    for a in range(2, -1, -1):
        c = np.floor((q[a] - grid_lo[a]) * to_cells)
        if not 0.0 <= c < dims[a]:
            return -1
        flat = flat * dims[a] + np.int64(c)
    return flat


@njit(cache=True, inline="always", error_model="numpy")
def _trace_hit(o, q, w, s, n, thinned, stop, grid_lo, to_cells, dims, lo, hi, cells, hits, misses, short):
    """Sample s of an occupied component of n samples: its hit in its own cell, its misses traced
    o -> `short`, the point `stop` (m, hit_stop) before q, whose cell gains no miss where it is q's
    own; `thinned` (3D): the misses thinned toward the sensor, else the ray whole."""
    weight = np.rint(w / WEIGHT_QUANTUM) * WEIGHT_QUANTUM  # the outermost level's (_trace_thinned)
    cell = _cell_of(q, grid_lo, to_cells, dims)
    if cell >= 0:
        hits[cell] += weight
    length = np.sqrt((q[0] - o[0]) ** 2 + (q[1] - o[1]) ** 2 + (q[2] - o[2]) ** 2)
    kept = 1.0 - stop / length
    if not kept > 0.0:  # the sample lies within the stop of the sensor: nothing between is claimed free
        return
    for a in range(3):
        short[a] = o[a] + kept * (q[a] - o[a])
    if thinned:
        _trace_thinned(o, short, w, s, n, grid_lo, to_cells, dims, lo, hi, cells, hits, misses)
    else:
        _trace_ray(
            o[0], o[1], o[2], short[0], short[1], short[2], w, False, False, grid_lo, to_cells, dims, lo, hi, 0, cells,
            hits, misses,
        )  # fmt: skip
    if cell >= 0 and _cell_of(short, grid_lo, to_cells, dims) == cell:
        misses[cell] -= weight


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_mixture(
    means, chol, counts, offsets, weights, thickness, key, is_hit, R, t, origin, grid_lo, grid_hi, to_cells, dims,
    hits, misses,
):  # fmt: skip
    """Trace every sample of one mixture (MixtureSamples' arrays), moved by (R, t), from the moved
    `origin`, with weight `weights[k]` (signed) each; grid_lo, grid_hi: the grid's box in 3D form
    (a 2D grid is one cell thick, its rays run at mid-height). Returns the samples traced."""
    d = means.shape[1]
    lo, hi = np.zeros(3), dims - 1.0  # every cell of the grid: _trace_ray's slab bounds
    cells = np.empty(dims[0] + dims[1] + dims[2] + 4, np.uint32)
    z, p, q, o, short = np.empty(d), np.empty(d), np.empty(3), np.empty(3), np.empty(3)
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
        w, stop = weights[k], hit_stop(1.0 / to_cells, thickness[k])
        for s in range(counts[k]):
            sample_normals(key, offsets[k] + s, z)
            for a in range(d):  # as sampling._place: the point in the node frame
                acc = 0.0
                for b in range(a + 1):
                    acc += chol[k, a, b] * z[b]
                p[a] = means[k, a] + acc
            for a in range(d):
                q[a] = _moved(R, t, p, a)
            if is_hit:
                _trace_hit(
                    o, q, w, s, counts[k], d == 3, stop, grid_lo, to_cells, dims, lo, hi, cells, hits, misses, short
                )
            elif d == 3:
                _trace_thinned(o, q, w, s, counts[k], grid_lo, to_cells, dims, lo, hi, cells, hits, misses)
            else:
                _trace_ray(
                    o[0], o[1], o[2], q[0], q[1], q[2], w, False, False, grid_lo, to_cells, dims, lo, hi, 0, cells,
                    hits, misses,
                )  # fmt: skip
        traced += counts[k]
    return traced


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_blocks(
    means,
    chol,
    counts,
    offsets,
    weights,
    thickness,
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
            means[lo:hi], chol[lo:hi], counts[lo:hi], offsets[lo:hi], weights[lo:hi], thickness[lo:hi], keys[b],
            is_hit[b], R[n], t[n], origins[n], grid_lo, grid_hi, to_cells, dims, hits, misses,
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
            np.concatenate([m.thickness for m in mixtures]),
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
