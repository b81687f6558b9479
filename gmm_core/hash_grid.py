"""A uniform hash grid over points, and per grid cell the mixture components whose box reaches it.

The E-steps of EM on points (gmm_core.em) and on voxels (gmm_core.voxel_em) score a point only
against the components listed for its cell, not all K; both visit the points in blocks, sorted by
cell within a block, so that a run of points shares one candidate list.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _hash_grid(points, n_components, max_cells):
    """A uniform grid over the points, (lo, cell size, dims).

    8 K^(1/d) cells along the longest axis keep a cell's candidate list near the few components
    that matter there (about 11-13 per point on 3D scans, against 13-18 with half as many); no
    more cells than points, so a sparse scan does not pay for the lists of empty cells.
    """
    n, d = points.shape
    lo = np.empty(d)
    extent = np.empty(d)
    for a in range(d):
        lo[a] = points[:, a].min()
        extent[a] = points[:, a].max() - lo[a]
    cell = max(extent.max() / (8.0 * n_components ** (1.0 / d)), 1e-9)
    dims = np.empty(d, dtype=np.int64)
    while True:
        n_cells = 1
        for a in range(d):
            dims[a] = max(1, min(int(extent[a] / cell) + 1, 256))
            n_cells *= dims[a]
        if n_cells <= max(max_cells, 1):
            return lo, cell, dims
        cell *= 1.25


@njit(cache=True)
def _cell_of(points, p, lo, cell, dims):
    # points and a row number, not the row points[p]: a row view costs an atomic increment and
    # decrement of the array's reference count per point.
    flat = 0
    for a in range(dims.shape[0]):
        i = int((points[p, a] - lo[a]) / cell)
        i = min(max(i, 0), dims[a] - 1)
        flat = flat * dims[a] + i
    return flat


@njit(cache=True)
def _candidates(weights, means, covs, lo, cell, dims, box_sigmas):
    """CSR lists: for each hash cell, the live components whose 5-sigma box overlaps it."""
    k_count, d = means.shape
    n_cells = 1
    for a in range(d):
        n_cells *= dims[a]
    first = np.empty((k_count, d), dtype=np.int64)
    last = np.empty((k_count, d), dtype=np.int64)
    counts = np.zeros(n_cells + 1, dtype=np.int64)
    for pass_ in range(2):
        fill = counts[:-1].copy() if pass_ == 1 else counts[:-1]
        items = np.empty(counts[-1] if pass_ == 1 else 0, dtype=np.int64)
        for k in range(k_count):
            if weights[k] == 0.0:  # a component that lost every point stays dead, as in scikit-learn
                continue
            for a in range(d):
                half = box_sigmas * np.sqrt(covs[k, a, a])
                first[k, a] = min(max(int((means[k, a] - half - lo[a]) / cell), 0), dims[a] - 1)
                last[k, a] = min(max(int((means[k, a] + half - lo[a]) / cell), 0), dims[a] - 1)
            idx = first[k].copy()
            while True:
                flat = 0
                for a in range(d):
                    flat = flat * dims[a] + idx[a]
                if pass_ == 0:
                    counts[flat] += 1
                else:
                    items[fill[flat]] = k
                    fill[flat] += 1
                # Odometer increment over the box of cells.
                a = d - 1
                while a >= 0 and idx[a] == last[k, a]:
                    idx[a] = first[k, a]
                    a -= 1
                if a < 0:
                    break
                idx[a] += 1
        if pass_ == 0:
            total = 0
            for c in range(n_cells):
                cnt = counts[c]
                counts[c] = total
                total += cnt
            counts[n_cells] = total
    return counts, items


@njit(cache=True)
def _block_cell_order(points, n_blocks, lo, cell, dims):
    """Counting sort of the points by block (point i in block i mod n_blocks), then by hash cell,
    so that points sharing a candidate list are visited together: (order, hash cell of each
    point in that order)."""
    n, d = points.shape
    n_cells = 1
    for a in range(d):
        n_cells *= dims[a]
    key = np.empty(n, dtype=np.int64)
    first = np.zeros(n_blocks * n_cells + 1, dtype=np.int64)
    for i in range(n):
        key[i] = (i % n_blocks) * n_cells + _cell_of(points, i, lo, cell, dims)
        first[key[i] + 1] += 1
    for c in range(n_blocks * n_cells):
        first[c + 1] += first[c]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[first[key[i]]] = i
        first[key[i]] += 1
    return order, key[order] % n_cells
