"""Voxel traversal of rays clipped to a grid, accumulating hits and misses: the cells of
Amanatides-Woo [22], found another way.

A ray crosses the same cells as Amanatides-Woo's walk, but the walk chooses the axis of each step
with a branch that the CPU mispredicts about every other step in 3D. Here each axis is taken on
its own: the cell a ray enters through its k-th boundary along x has x = first + s (k + 1) and y, z
the floor of the ray's coordinates at that boundary, linear in k. Three short loops without
branches write those cells (vectorised), and one loop adds the misses. The boundary crossed last
(largest t) enters the end cell, which takes the hit.

One kernel serves 2D and 3D: a 2D grid is a 3D grid one cell thick with every ray at its
mid-plane, so the z axis never steps.

Rays are first copied into one array of records (end, weight, origin and hit flag): on a grid too
big for the cache, in the order of the block of BLOCK^3 cells their end point falls in, not in the
order given: rays that end close together cross nearly the same cells, so the counts they add to
stay in cache. The block order puts the slowest array axis (z in 3D, y in 2D) first, so the equal
chunks of ordered rays given to the numba threads each reach only a slab of that axis. The first
chunk adds into the result itself, every other one into a buffer that holds only its slab, and
the buffers are added in at the end: a thread never zeroes, fills or sums a whole copy of a big
grid. Each chunk and the buffers' sum run in a fixed order, so the same rays and thread count give
the same sums, bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid

BLOCK = 4  # cells along each side of the blocks that rays are ordered by (2 to 8 measured alike)
# Sort only grids whose float64 misses (8 bytes a cell) are half a 2 MB L2 cache or more: measured
# with 10 m rays in random directions, sorting gained 1.1x on 168k cells (2D, 0.05 m), 1.7x on
# 551k cells (3D, 0.25 m) and 2.7x on 8.6M (3D, 0.1 m).
SORT_MIN_CELLS = 2**17
MAX_CELLS = 2**31 - 1  # a traced grid's cells are numbered in 32 bits (_enter)
MARGIN = 2  # cells added to each side of a chunk's slab: the traversal's round-off stays within one
END, WEIGHT, CODE = 0, 3, 4  # columns of a ray record: end x, y, z; weight; 2 * origin index + is_hit


@njit(cache=True, inline="always")
def _cell(p, lo, per_cell, first, last):
    """The cell of coordinate p along one axis (cells of 1 / per_cell from lo), clamped to
    [first, last] before the float becomes an int (a point far outside the grid must not overflow)."""
    return np.int64(min(max(np.floor((p - lo) * per_cell), first), last))


@njit(cache=True, inline="always")
def _put(rays, i, ray_origin, ends, weights, is_hit, r):
    """Ray r as record i."""
    for a in range(3):
        rays[i, END + a] = ends[r, a]
    rays[i, WEIGHT] = weights[r]
    rays[i, CODE] = 2 * ray_origin[r] + is_hit[r]


@njit(cache=True, nogil=True, error_model="numpy")
def _pack_rays(ray_origin, ends, weights, is_hit, grid_origin, resolution, dims, sort, rays, keys):
    """Fill `rays` with the rays as records (columns END.., WEIGHT, CODE), sorted (stable counting
    sort) by the block of their end point, clamped into the grid, with blocks numbered z, then y,
    then x, when `sort` (`keys`: room for each ray's block). Copies, not an index: reading rays
    through a random index stalls the traversal on every ray; one array of records is also written
    faster than five arrays. Indices are unsigned where they can be: numba then skips the
    wrap-around of negative indices."""
    n = ends.shape[0]
    if not sort:
        for r in range(n):
            _put(rays, r, ray_origin, ends, weights, is_hit, r)
        return
    n_blocks = (dims + BLOCK - 1) // BLOCK
    per_block = 1.0 / (resolution * BLOCK)
    for r in range(n):  # no other work in this loop: it vectorises
        key = 0
        for a in range(2, -1, -1):
            key = key * n_blocks[a] + _cell(ends[r, a], grid_origin[a], per_block, 0, n_blocks[a] - 1)
        keys[r] = key
    start = np.zeros(n_blocks[0] * n_blocks[1] * n_blocks[2] + 1, np.uint64)
    for key in keys:
        start[key + 1] += 1
    start = np.cumsum(start)
    for r in range(n):
        i = start[keys[r]]
        start[keys[r]] = i + np.uint64(1)
        _put(rays, i, ray_origin, ends, weights, is_hit, r)


@njit(cache=True)
def _chunk_boxes(origins, rays, grid_origin, resolution, dims, axis, n_chunks):
    """Per chunk of rays, the cells [box[c, 0], box[c, 1]) it may reach: the whole grid but
    along `axis`, where it spans the chunk's sensor origins and end points (a segment stays
    between its ends), widened by MARGIN and clamped to the grid."""
    boxes = np.zeros((n_chunks, 2, 3), np.int64)
    n = rays.shape[0]
    for c in range(n_chunks):
        boxes[c, 1] = dims
        lo, hi = np.inf, -np.inf
        for r in range(n * c // n_chunks, n * (c + 1) // n_chunks):
            o = origins[np.int64(rays[r, CODE]) >> 1, axis]
            lo = min(lo, o, rays[r, END + axis])
            hi = max(hi, o, rays[r, END + axis])
        if lo > hi:  # no rays
            boxes[c, 1, axis] = 0
            continue
        boxes[c, 0, axis] = _cell(lo, grid_origin[axis], 1.0 / resolution, 0, dims[axis]) - MARGIN
        boxes[c, 1, axis] = _cell(hi, grid_origin[axis], 1.0 / resolution, 0, dims[axis]) + MARGIN + 1
        boxes[c, 0, axis] = max(boxes[c, 0, axis], 0)
        boxes[c, 1, axis] = min(boxes[c, 1, axis], dims[axis])
    return boxes


@njit(cache=True, inline="always")
def _slab(uo, ud, inv, n, t0, t1):
    """Liang-Barsky: [t0, t1] narrowed to where uo + t ud lies in [0, n] (cell units)."""
    if ud == 0.0:
        return (t0, t1) if 0.0 <= uo <= n else (1.0, 0.0)
    ta, tb = -uo * inv, (n - uo) * inv
    return max(t0, min(ta, tb)), min(t1, max(ta, tb))


@njit(cache=True, inline="always")
def _axis(uo, ud, t0, t1, n):
    """Along one axis (cell units): first cell, last cell, step (-1, 0, 1), and the coordinate
    of the first boundary crossed. Branch-free: the signs of ud are random from ray to ray."""
    first = _cell(uo + t0 * ud, 0.0, 1.0, 0, n - 1)
    last = _cell(uo + t1 * ud, 0.0, 1.0, 0, n - 1)
    up = np.int64(ud > 0.0)
    return first, last, up - np.int64(ud < 0.0), np.float64(first + up)


@njit(cache=True)
def _enter(cells, at, n, flat, step, ub, dub, lob, hib, stride_b, uc, duc, loc, hic, stride_c):
    """cells[at:at + n]: the cells entered through n successive boundaries of one axis. At the
    k-th the index along that axis is flat + k step (flattened, in place), the other two axes'
    coordinates are ub + k dub and uc + k duc, floored and clamped to [lob, hib], [loc, hic].

    The loop runs a multiple of 4 times, so the vector loop needs no scalar tail (a mispredicted
    exit fewer per axis): up to 3 entries past at + n are scratch, which the caller leaves room
    for and overwrites or ignores."""
    # Indexed from an unsigned base, not through a view cells[at:]: no wrap-around of negative
    # indices, so the stores vectorise, and no view is made (three views cost about 40 ns of a
    # ray's 130-340 ns, docs/BENCHMARKS.md). Cells are 32-bit and k counts in 32 bits: AVX2 has
    # packed conversions between float64 and int32 only, and with 64-bit ones the loop converted
    # lane by lane (the trace took 1.4-1.9x as long on an AVX2 EPYC, docs/BENCHMARKS.md).
    base = np.uint64(at)
    for k in range(np.int32((n + 3) & -4)):
        kf = np.float64(np.int32(k))
        b = min(max(np.floor(ub + kf * dub), lob), hib)
        c = min(max(np.floor(uc + kf * duc), loc), hic)
        cells[base + np.uint64(k)] = np.uint32(np.int32(flat + kf * step + b * stride_b + c * stride_c))
    return at + n


@njit(cache=True, inline="always", error_model="numpy")  # 1 / 0 is inf: an axis the ray does not move along
def _trace_ray(
    ox, oy, oz, ex, ey, ez, w, is_hit, skip_start, grid_origin, to_cells, dims, lo, hi, offset, cells, hits, misses
):
    """Trace one ray (ox, oy, oz) -> (ex, ey, ez) of weight w: cell (x, y, z) of the grid is entry
    (z ny + y) nx + x - offset of hits and misses, which hold the cells [lo, hi] (float, inclusive)
    along the slowest axis; `cells`: scratch of nx + ny + nz + 4 entries. `skip_start`: the cell
    of the start point gains nothing when that point is inside the grid (the ray entered that cell
    before it: a segment of a longer ray, gmm_core.scan_trace)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    sy, sz = np.float64(nx), np.float64(nx * ny)  # strides of y and z in the flat index
    # Cell units: the grid is [0, n) along each axis and the ray is u(t) = uo + t ud, t in [0, 1].
    uox, udx = (ox - grid_origin[0]) * to_cells, (ex - ox) * to_cells
    uoy, udy = (oy - grid_origin[1]) * to_cells, (ey - oy) * to_cells
    uoz, udz = (oz - grid_origin[2]) * to_cells, (ez - oz) * to_cells
    ix, iy, iz = 1.0 / udx, 1.0 / udy, 1.0 / udz
    t0, t1 = _slab(uox, udx, ix, nx, 0.0, 1.0)
    t0, t1 = _slab(uoy, udy, iy, ny, t0, t1)
    t0, t1 = _slab(uoz, udz, iz, nz, t0, t1)
    # A ray that misses the grid is not returned from early: it goes on as a ray of weight 0 that
    # crosses nothing from the first cell held. With one exit, numba's reference counts of cells,
    # hits and misses pair up and are pruned; an early return left three atomic increments and
    # three decrements a ray, about 15 % of a 3D ray's time (docs/BENCHMARKS.md).
    x, x_last, step_x, bx = _axis(uox, udx, t0, t1, nx)
    y, y_last, step_y, by = _axis(uoy, udy, t0, t1, ny)
    z, z_last, step_z, bz = _axis(uoz, udz, t0, t1, nz)
    if t0 > t1:
        w = 0.0
        x = x_last = np.int64(lo[0])
        y = y_last = np.int64(lo[1])
        z = z_last = np.int64(lo[2])
    n_x, n_y, n_z = abs(x_last - x), abs(y_last - y), abs(z_last - z)
    tx, ty, tz = (bx - uox) * ix, (by - uoy) * iy, (bz - uoz) * iz  # t of the first boundaries
    cells[0] = np.uint32((z * ny + y) * nx + x - offset)
    at = _enter(
        cells,
        1,
        n_x,
        np.float64(x + step_x - offset),
        np.float64(step_x),
        uoy + tx * udy,
        step_x * ix * udy,
        lo[1],
        hi[1],
        sy,
        uoz + tx * udz,
        step_x * ix * udz,
        lo[2],
        hi[2],
        sz,
    )
    at = _enter(
        cells,
        at,
        n_y,
        (y + step_y) * sy - offset,
        step_y * sy,
        uox + ty * udx,
        step_y * iy * udx,
        lo[0],
        hi[0],
        1.0,
        uoz + ty * udz,
        step_y * iy * udz,
        lo[2],
        hi[2],
        sz,
    )
    at = _enter(
        cells,
        at,
        n_z,
        (z + step_z) * sz - offset,
        step_z * sz,
        uox + tz * udx,
        step_z * iz * udx,
        lo[0],
        hi[0],
        1.0,
        uoy + tz * udy,
        step_z * iz * udy,
        lo[1],
        hi[1],
        sy,
    )
    # The end cell: the last one of the axis whose last boundary comes latest (the start cell
    # when the ray crosses none). Swapped to the back, it stays out of the loop of misses.
    t_x = tx + (n_x - 1) * abs(ix) if n_x > 0 else -1.0
    t_y = ty + (n_y - 1) * abs(iy) if n_y > 0 else -1.0
    t_z = tz + (n_z - 1) * abs(iz) if n_z > 0 else -1.0
    x_ends = (t_x >= t_y) & (t_x >= t_z)
    y_ends = (t_y >= t_z) & ~x_ends
    end = n_x if x_ends else (n_x + n_y if y_ends else at - 1)
    end_cell = cells[end]
    cells[end] = cells[at - 1]
    skip = skip_start and t0 == 0.0  # a start point outside: the grid is entered on this ray
    if skip and at == 1:  # no boundary crossed: the end cell is the start cell
        w = 0.0
    for i in range(np.int64(skip), at - 1):
        misses[cells[i]] += w
    # The end cell holds the sample only when the ray ends inside the grid (t1 == 1).
    h = w if is_hit and t1 >= 1.0 else 0.0
    hits[end_cell] += h
    misses[end_cell] += w - h


@njit(cache=True, inline="always")
def box_bounds(box):
    """The first and last cell along each axis of the cells [box[0], box[1]), as floats (_trace_ray's lo, hi)."""
    lo, hi = np.empty(3), np.empty(3)
    for a in range(3):
        lo[a], hi[a] = np.float64(box[0, a]), np.float64(box[1, a] - 1)
    return lo, hi


@njit(cache=True, error_model="numpy")
def _trace_chunk(origins, rays, first_ray, last_ray, grid_origin, resolution, dims, box, offset, hits, misses):
    """Trace rays first_ray:last_ray; cell (x, y, z) of the grid is entry (z ny + y) nx + x - offset
    of hits and misses, which hold the cells of `box` along the slowest axis."""
    lo, hi = box_bounds(box)
    to_cells = 1.0 / resolution
    cells = np.empty(dims[0] + dims[1] + dims[2] + 4, np.uint32)  # start cell, crossings, _enter's 3 of scratch
    for r in range(first_ray, last_ray):
        code = np.int64(rays[r, CODE])
        o = code >> 1
        _trace_ray(
            origins[o, 0],
            origins[o, 1],
            origins[o, 2],
            rays[r, END],
            rays[r, END + 1],
            rays[r, END + 2],
            rays[r, WEIGHT],
            code & 1,
            False,
            grid_origin,
            to_cells,
            dims,
            lo,
            hi,
            offset,
            cells,
            hits,
            misses,
        )


@njit(cache=True, parallel=True, nogil=True)  # the caller's other Python threads run while it traces
def _trace(origins, rays, grid_origin, resolution, dims, sorted_, n_chunks, hits, misses):
    axis = 2 if dims[2] > 1 else 1  # the slowest array axis that has more than one cell
    stride = dims[0] if axis == 1 else dims[0] * dims[1]
    if sorted_:
        boxes = _chunk_boxes(origins, rays, grid_origin, resolution, dims, axis, n_chunks)
    else:  # a small grid: every chunk gets all of it, sparing the pass over the rays
        boxes = np.zeros((n_chunks, 2, 3), np.int64)
        boxes[:, 1] = dims
    # Chunk c >= 1 adds into buffer entries start[c]:start[c + 1], its slab of the grid.
    start = np.zeros(n_chunks + 1, np.int64)
    for c in range(1, n_chunks):
        start[c + 1] = start[c] + (boxes[c, 1, axis] - boxes[c, 0, axis]) * stride
    hit_buffer, miss_buffer = np.zeros(start[-1]), np.zeros(start[-1])
    n_rays = rays.shape[0]
    for c in prange(n_chunks):
        first, last = n_rays * c // n_chunks, n_rays * (c + 1) // n_chunks
        if c == 0:  # into the grid itself
            h, m, offset = hits, misses, 0
        else:
            h, m, offset = (
                hit_buffer[start[c] : start[c + 1]],
                miss_buffer[start[c] : start[c + 1]],
                boxes[c, 0, axis] * stride,
            )
        _trace_chunk(origins, rays, first, last, grid_origin, resolution, dims, boxes[c], offset, h, m)
    for c in range(1, n_chunks):
        cells = slice(boxes[c, 0, axis] * stride, boxes[c, 1, axis] * stride)
        hits[cells] += hit_buffer[start[c] : start[c + 1]]
        misses[cells] += miss_buffer[start[c] : start[c + 1]]


@njit(cache=True, nogil=True)
def _trace_serial(origins, rays, grid_origin, resolution, dims, hits, misses):
    """`_trace` on the calling thread alone, outside numba's threading layer: callers that trace
    from threads of their own (a map server's requests) need no lock around it."""
    box = np.zeros((2, 3), np.int64)
    box[1] = dims
    zero = np.int64(0)  # not the literal 0, which numba would compile _trace_chunk once more for
    _trace_chunk(origins, rays, zero, rays.shape[0], grid_origin, resolution, dims, box, zero, hits, misses)


def _counts(origins, ray_origin, ends, weights, is_hit, grid_origin, resolution, dims, n_chunks):
    """Flat hit and miss counts of rays in 3D form (see trace_rays), traced in n_chunks. The large
    arrays come from numpy, whose allocator asks for huge pages: numba's faults them in 4 kB pages,
    which took 11 of the 32 ms of packing 10^6 rays."""
    n_cells = int(np.prod(dims))
    sort = n_cells >= SORT_MIN_CELLS
    rays, keys = np.empty((len(ends), 5)), np.empty(len(ends) if sort else 0, np.uint64)
    _pack_rays(ray_origin, ends, weights, is_hit, grid_origin, resolution, dims, sort, rays, keys)
    hits, misses = np.zeros(n_cells), np.zeros(n_cells)
    if n_chunks == 1:
        _trace_serial(origins, rays, grid_origin, resolution, dims, hits, misses)
    else:
        _trace(origins, rays, grid_origin, resolution, dims, sort, n_chunks, hits, misses)
    return hits, misses


def check_cells(grid: Grid) -> None:
    """Refuse a grid whose cells 32-bit indices cannot number (the tracer's limit, MAX_CELLS)."""
    if grid.n_cells > MAX_CELLS:
        raise ValueError(f"grid: {grid.n_cells} cells is more than the {MAX_CELLS} a trace can number")


def _as_3d(points: np.ndarray, dim: int, z: float) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, dim)
    if dim == 3:
        return np.ascontiguousarray(points)
    return np.ascontiguousarray(np.column_stack([points, np.full(len(points), z)]))


def trace_rays(
    grid: Grid,
    origins: np.ndarray,
    ray_origin: np.ndarray,
    ends: np.ndarray,
    weights: np.ndarray,
    is_hit: np.ndarray,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Hit and miss counts on `grid` from rays origins[ray_origin[r]] -> ends[r].

    Every cell a ray crosses inside the grid gains `weights[r]` misses, except the cell of its
    end point when `is_hit[r]` (that one gains a hit). Rays are clipped to the grid, so a ray
    ending outside adds misses only. Returns float64 arrays of `grid.array_shape`: sums in double
    precision do not depend, to float32 precision, on how the rays were split among threads, and
    the same rays give the same sums.

    `threads`: numba's threads (default: numba.get_num_threads()); 1 traces on the calling
    thread, safe to call from several threads at once (the threading layer may not be).
    """
    check_cells(grid)
    d = grid.dim
    z_mid = 0.5 * grid.resolution  # 2D: rays run along the mid-plane of a one-cell-thick grid
    grid_origin = _as_3d(grid.origin, d, 0.0)[0]
    dims = np.array(list(grid.shape) + ([1] if d == 2 else []), dtype=np.int64)
    rays = (
        _as_3d(origins, d, z_mid),
        np.ascontiguousarray(ray_origin, dtype=np.int64),
        _as_3d(ends, d, z_mid),
        np.ascontiguousarray(weights, dtype=np.float64),
        np.ascontiguousarray(is_hit, dtype=np.bool_),
        grid_origin,
        grid.resolution,
        dims,
    )
    hits, misses = _counts(*rays, threads or numba.get_num_threads())
    return hits.reshape(grid.array_shape), misses.reshape(grid.array_shape)
