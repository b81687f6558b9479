"""Amanatides-Woo voxel traversal [22] of rays clipped to a grid, accumulating hits and misses.

One kernel serves 2D and 3D: a 2D grid is a 3D grid one cell thick with every ray at its
mid-plane, so the z axis never steps.

On a grid too big for the cache, rays are traced in the order of the block of BLOCK^3 cells
their end point falls in, not in the order given: rays that end close together cross nearly the
same cells, so the counts they add to stay in cache. The block order puts the slowest array axis
(z in 3D, y in 2D) first, so the equal chunks of ordered rays given to the numba threads each
reach only a slab of that axis. The first chunk adds into the result itself, every other one
into a buffer that holds only its slab, and the buffers are added in at the end: a thread never
zeroes, fills or sums a whole copy of a big grid. Each chunk and the buffers' sum run in a fixed
order, so the same rays and thread count give the same sums, bit for bit.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid

BLOCK = 4  # cells along each side of the blocks that rays are ordered by (2 to 4 measured best)
# Sort only grids whose float64 hits and misses (16 bytes a cell) are four times a 2 MB L2 cache
# or more: measured with 10 m rays in random directions, sorting lost 8% on 168k cells (2D, 0.05 m)
# and gained 1.25x on 551k cells (3D, 0.25 m), 2.1-2.5x on 8.6M (3D, 0.1 m); on a 512 x 512 tile of
# the Intel map (262k cells) it lost 10% (bench/correction.py, 146-155 vs 132-134 ms).
SORT_MIN_CELLS = 2**19
MARGIN = 2  # cells added to each side of a chunk's slab: the traversal's round-off stays within one


@njit(cache=True, inline="always")
def _clip(o, e, lo, hi):
    """Liang-Barsky: the parameter range [t0, t1] of o + t (e - o), t in [0, 1], inside [lo, hi]."""
    t0, t1 = 0.0, 1.0
    for a in range(3):
        delta = e[a] - o[a]
        if delta == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
            continue
        ta = (lo[a] - o[a]) / delta
        tb = (hi[a] - o[a]) / delta
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    return t0, t1


@njit(cache=True, inline="always")
def _cell(p, lo, resolution, first, last):
    """The cell of coordinate p along one axis, clamped to [first, last] before the float becomes
    an int (a point far outside the grid must not overflow)."""
    return int(min(max(np.floor((p - lo) / resolution), first), last))


@njit(cache=True, inline="always")
def _axis_start(o, e, t0, t1, lo, resolution, n):
    """Per axis: first cell, last cell, step, t of the first boundary, t between boundaries."""
    delta = e - o
    p0 = o + t0 * delta
    first = _cell(p0, lo, resolution, 0, n - 1)
    last = _cell(o + t1 * delta, lo, resolution, 0, n - 1)
    if delta > 0.0:
        return first, last, 1, (lo + (first + 1) * resolution - p0) / delta, resolution / delta
    if delta < 0.0:
        return first, last, -1, (lo + first * resolution - p0) / delta, -resolution / delta
    return first, last, 0, np.inf, np.inf


@njit(cache=True)
def _sort_rays(ray_origin, ends, weights, is_hit, grid_origin, resolution, dims):
    """The rays sorted (stable counting sort) by the block of their end point, clamped into the
    grid, with blocks numbered z, then y, then x. Copies, not an index: reading rays through a
    random index stalls the traversal on every ray."""
    n_blocks = (dims + BLOCK - 1) // BLOCK
    n = ends.shape[0]
    keys = np.empty(n, np.int64)
    for r in range(n):
        key = 0
        for a in range(2, -1, -1):
            block = _cell(ends[r, a], grid_origin[a], resolution * BLOCK, 0, n_blocks[a] - 1)
            key = key * n_blocks[a] + block
        keys[r] = key
    start = np.zeros(n_blocks[0] * n_blocks[1] * n_blocks[2] + 1, np.int64)
    for key in keys:
        start[key + 1] += 1
    start = np.cumsum(start)
    sorted_origin, sorted_ends = np.empty_like(ray_origin), np.empty_like(ends)
    sorted_weights, sorted_hit = np.empty_like(weights), np.empty_like(is_hit)
    for r in range(n):
        i = start[keys[r]]
        start[keys[r]] += 1
        sorted_origin[i] = ray_origin[r]
        for a in range(3):
            sorted_ends[i, a] = ends[r, a]
        sorted_weights[i] = weights[r]
        sorted_hit[i] = is_hit[r]
    return sorted_origin, sorted_ends, sorted_weights, sorted_hit


@njit(cache=True)
def _chunk_boxes(origins, ray_origin, ends, grid_origin, resolution, dims, axis, n_chunks):
    """Per chunk of rays, the cells [box[c, 0], box[c, 1]) it may reach: the whole grid but
    along `axis`, where it spans the chunk's sensor origins and end points (a segment stays
    between its ends), widened by MARGIN and clamped to the grid."""
    boxes = np.zeros((n_chunks, 2, 3), np.int64)
    n = ends.shape[0]
    for c in range(n_chunks):
        boxes[c, 1] = dims
        lo, hi = np.inf, -np.inf
        for r in range(n * c // n_chunks, n * (c + 1) // n_chunks):
            o = origins[ray_origin[r], axis]
            lo = min(lo, o, ends[r, axis])
            hi = max(hi, o, ends[r, axis])
        if lo > hi:  # no rays
            boxes[c, 1, axis] = 0
            continue
        boxes[c, 0, axis] = _cell(lo, grid_origin[axis], resolution, 0, dims[axis]) - MARGIN
        boxes[c, 1, axis] = _cell(hi, grid_origin[axis], resolution, 0, dims[axis]) + MARGIN + 1
        boxes[c, 0, axis] = max(boxes[c, 0, axis], 0)
        boxes[c, 1, axis] = min(boxes[c, 1, axis], dims[axis])
    return boxes


@njit(cache=True)
def _trace_chunk(origins, ray_origin, ends, weights, is_hit, first, last,
                 grid_origin, resolution, dims, box, offset, hits, misses):
    """Trace rays first:last; cell (x, y, z) of the grid is entry (z ny + y) nx + x - offset
    of hits and misses, which hold the cells of `box` along the slowest axis."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    x_lo, y_lo, z_lo = box[0, 0], box[0, 1], box[0, 2]
    x_hi, y_hi, z_hi = box[1, 0], box[1, 1], box[1, 2]
    hi = grid_origin + dims * resolution
    for r in range(first, last):
        o = origins[ray_origin[r]]
        e = ends[r]
        t0, t1 = _clip(o, e, grid_origin, hi)
        if t0 > t1:
            continue
        x, x_last, sx, tx, dtx = _axis_start(o[0], e[0], t0, t1, grid_origin[0], resolution, nx)
        y, y_last, sy, ty, dty = _axis_start(o[1], e[1], t0, t1, grid_origin[1], resolution, ny)
        z, z_last, sz, tz, dtz = _axis_start(o[2], e[2], t0, t1, grid_origin[2], resolution, nz)
        n_steps = abs(x_last - x) + abs(y_last - y) + abs(z_last - z)
        flat = (z * ny + y) * nx + x - offset
        w = weights[r]
        for _ in range(n_steps):
            misses[flat] += w
            # Step along the axis whose next boundary is nearest; round-off may point one step
            # off the box at the very end, so stop there rather than leave it.
            if tx <= ty and tx <= tz:
                x += sx
                if x < x_lo or x >= x_hi:
                    break
                tx += dtx
                flat += sx
            elif ty <= tz:
                y += sy
                if y < y_lo or y >= y_hi:
                    break
                ty += dty
                flat += sy * nx
            else:
                z += sz
                if z < z_lo or z >= z_hi:
                    break
                tz += dtz
                flat += sz * nx * ny
        # The end cell holds the sample only when the ray ends inside the grid (t1 == 1).
        if is_hit[r] and t1 >= 1.0:
            hits[flat] += w
        else:
            misses[flat] += w


@njit(cache=True, parallel=True, nogil=True)  # the caller's other Python threads run while it traces
def _trace(origins, ray_origin, ends, weights, is_hit, grid_origin, resolution, dims, n_chunks):
    n_cells = dims[0] * dims[1] * dims[2]
    axis = 2 if dims[2] > 1 else 1  # the slowest array axis that has more than one cell
    stride = dims[0] if axis == 1 else dims[0] * dims[1]
    if n_cells >= SORT_MIN_CELLS:
        ray_origin, ends, weights, is_hit = _sort_rays(ray_origin, ends, weights, is_hit,
                                                       grid_origin, resolution, dims)
        boxes = _chunk_boxes(origins, ray_origin, ends, grid_origin, resolution, dims, axis, n_chunks)
    else:  # a small grid: every chunk gets all of it, sparing the pass over the rays
        boxes = np.zeros((n_chunks, 2, 3), np.int64)
        boxes[:, 1] = dims
    # Chunk c >= 1 adds into buffer entries start[c]:start[c + 1], its slab of the grid.
    start = np.zeros(n_chunks + 1, np.int64)
    for c in range(1, n_chunks):
        start[c + 1] = start[c] + (boxes[c, 1, axis] - boxes[c, 0, axis]) * stride
    hits, misses = np.zeros(n_cells), np.zeros(n_cells)
    hit_buffer, miss_buffer = np.zeros(start[-1]), np.zeros(start[-1])
    n_rays = ends.shape[0]
    for c in prange(n_chunks):
        first, last = n_rays * c // n_chunks, n_rays * (c + 1) // n_chunks
        if c == 0:
            _trace_chunk(origins, ray_origin, ends, weights, is_hit, first, last,
                         grid_origin, resolution, dims, boxes[c], 0, hits, misses)
        else:
            _trace_chunk(origins, ray_origin, ends, weights, is_hit, first, last,
                         grid_origin, resolution, dims, boxes[c], boxes[c, 0, axis] * stride,
                         hit_buffer[start[c]:start[c + 1]], miss_buffer[start[c]:start[c + 1]])
    for c in range(1, n_chunks):
        cells = slice(boxes[c, 0, axis] * stride, boxes[c, 1, axis] * stride)
        hits[cells] += hit_buffer[start[c]:start[c + 1]]
        misses[cells] += miss_buffer[start[c]:start[c + 1]]
    return hits, misses


@njit(cache=True, nogil=True)
def _trace_serial(origins, ray_origin, ends, weights, is_hit, grid_origin, resolution, dims):
    """`_trace` on the calling thread alone, outside numba's threading layer: callers that trace
    from threads of their own (a map server's requests) need no lock around it."""
    n_cells = dims[0] * dims[1] * dims[2]
    if n_cells >= SORT_MIN_CELLS:
        ray_origin, ends, weights, is_hit = _sort_rays(ray_origin, ends, weights, is_hit,
                                                       grid_origin, resolution, dims)
    box = np.zeros((2, 3), np.int64)
    box[1] = dims
    hits, misses = np.zeros(n_cells), np.zeros(n_cells)
    _trace_chunk(origins, ray_origin, ends, weights, is_hit, 0, ends.shape[0],
                 grid_origin, resolution, dims, box, 0, hits, misses)
    return hits, misses


def _as_3d(points: np.ndarray, dim: int, z: float) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, dim)
    if dim == 3:
        return np.ascontiguousarray(points)
    return np.ascontiguousarray(np.column_stack([points, np.full(len(points), z)]))


def trace_rays(grid: Grid, origins: np.ndarray, ray_origin: np.ndarray, ends: np.ndarray,
               weights: np.ndarray, is_hit: np.ndarray, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Hit and miss counts on `grid` from rays origins[ray_origin[r]] -> ends[r].

    Every cell a ray crosses inside the grid gains `weights[r]` misses, except the cell of its
    end point when `is_hit[r]` (that one gains a hit). Rays are clipped to the grid, so a ray
    ending outside adds misses only. Returns float64 arrays of `grid.array_shape`: sums in double
    precision do not depend, to float32 precision, on how the rays were split among threads, and
    the same rays give the same sums.

    `threads`: numba's threads (default: numba.get_num_threads()); 1 traces on the calling
    thread, safe to call from several threads at once (the threading layer may not be).
    """
    d = grid.dim
    z_mid = 0.5 * grid.resolution  # 2D: rays run along the mid-plane of a one-cell-thick grid
    grid_origin = _as_3d(grid.origin, d, 0.0)[0]
    dims = np.array(list(grid.shape) + ([1] if d == 2 else []), dtype=np.int64)
    rays = (_as_3d(origins, d, z_mid), np.ascontiguousarray(ray_origin, dtype=np.int64), _as_3d(ends, d, z_mid),
            np.ascontiguousarray(weights, dtype=np.float64), np.ascontiguousarray(is_hit, dtype=np.bool_),
            grid_origin, grid.resolution, dims)
    threads = threads or numba.get_num_threads()
    hits, misses = _trace_serial(*rays) if threads == 1 else _trace(*rays, threads)
    return hits.reshape(grid.array_shape), misses.reshape(grid.array_shape)
