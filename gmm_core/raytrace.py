"""Amanatides-Woo voxel traversal [22] of rays clipped to a grid, accumulating hits and misses.

One kernel serves 2D and 3D: a 2D grid is a 3D grid one cell thick with every ray at its
mid-plane, so the z axis never steps. Rays are split into one chunk per numba thread, each
thread adding into its own copy of the counts, summed at the end (counts are additive).
"""
from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid


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
def _axis_start(o, e, t0, t1, lo, resolution, n):
    """Per axis: first cell, last cell, step, t of the first boundary, t between boundaries."""
    delta = e - o
    p0 = o + t0 * delta
    first = min(max(int(np.floor((p0 - lo) / resolution)), 0), n - 1)
    last = min(max(int(np.floor((o + t1 * delta - lo) / resolution)), 0), n - 1)
    if delta > 0.0:
        return first, last, 1, (lo + (first + 1) * resolution - p0) / delta, resolution / delta
    if delta < 0.0:
        return first, last, -1, (lo + first * resolution - p0) / delta, -resolution / delta
    return first, last, 0, np.inf, np.inf


@njit(cache=True)
def _trace_chunk(origins, ray_origin, ends, weights, is_hit, first, last,
                 grid_origin, resolution, dims, hits, misses):
    nx, ny, nz = dims[0], dims[1], dims[2]
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
        flat = (z * ny + y) * nx + x
        w = weights[r]
        for _ in range(n_steps):
            misses[flat] += w
            # Step along the axis whose next boundary is nearest; round-off may point one step
            # off the grid at the very end, so stop there rather than leave it.
            if tx <= ty and tx <= tz:
                x += sx
                if x < 0 or x >= nx:
                    break
                tx += dtx
                flat += sx
            elif ty <= tz:
                y += sy
                if y < 0 or y >= ny:
                    break
                ty += dty
                flat += sy * nx
            else:
                z += sz
                if z < 0 or z >= nz:
                    break
                tz += dtz
                flat += sz * nx * ny
        # The end cell holds the sample only when the ray ends inside the grid (t1 == 1).
        if is_hit[r] and t1 >= 1.0:
            hits[flat] += w
        else:
            misses[flat] += w


@njit(cache=True, parallel=True, nogil=True)  # a map server keeps ingesting while a tile is traced
def _trace(origins, ray_origin, ends, weights, is_hit, grid_origin, resolution, dims, n_chunks):
    n_cells = dims[0] * dims[1] * dims[2]
    hits = np.zeros((n_chunks, n_cells))
    misses = np.zeros((n_chunks, n_cells))
    n_rays = ends.shape[0]
    for c in prange(n_chunks):
        first = n_rays * c // n_chunks
        last = n_rays * (c + 1) // n_chunks
        _trace_chunk(origins, ray_origin, ends, weights, is_hit, first, last,
                     grid_origin, resolution, dims, hits[c], misses[c])
    return hits, misses


def _as_3d(points: np.ndarray, dim: int, z: float) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, dim)
    if dim == 3:
        return np.ascontiguousarray(points)
    return np.ascontiguousarray(np.column_stack([points, np.full(len(points), z)]))


def trace_rays(grid: Grid, origins: np.ndarray, ray_origin: np.ndarray, ends: np.ndarray,
               weights: np.ndarray, is_hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit and miss counts on `grid` from rays origins[ray_origin[r]] -> ends[r].

    Every cell a ray crosses inside the grid gains `weights[r]` misses, except the cell of its
    end point when `is_hit[r]` (that one gains a hit). Rays are clipped to the grid, so a ray
    ending outside adds misses only. Returns float64 arrays of `grid.array_shape`: sums in double
    precision do not depend, to float32 precision, on how the rays were split among threads.
    """
    d = grid.dim
    z_mid = 0.5 * grid.resolution  # 2D: rays run along the mid-plane of a one-cell-thick grid
    grid_origin = _as_3d(grid.origin, d, 0.0)[0]
    dims = np.array(list(grid.shape) + ([1] if d == 2 else []), dtype=np.int64)
    n_chunks = numba.get_num_threads()
    hits, misses = _trace(_as_3d(origins, d, z_mid), np.ascontiguousarray(ray_origin, dtype=np.int64),
                          _as_3d(ends, d, z_mid), np.ascontiguousarray(weights, dtype=np.float64),
                          np.ascontiguousarray(is_hit, dtype=np.bool_), grid_origin, grid.resolution,
                          dims, n_chunks)
    shape = grid.array_shape
    if n_chunks == 1:
        return hits[0].reshape(shape), misses[0].reshape(shape)
    return hits.sum(axis=0).reshape(shape), misses.sum(axis=0).reshape(shape)
