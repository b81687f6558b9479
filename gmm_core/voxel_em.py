"""A 3D scan's mixture from the sufficient statistics of a fine voxelisation, at sensor rate.

Three steps, each one pass over its data:

1. One pass over the points sums [1, x, x x^T] per voxel of size `voxel_size` (a hash table;
   consecutive points of a scan line mostly fall in the voxel of the point before).
2. Top-down splitting of those voxels (hierarchical, as Eckart et al., CVPR 2016, ref. [10] of
   the paper): the group with the largest scatter (sum of squared distances to its mean, what
   k-means minimises) is cut at its mean across its principal axis until there are K groups;
   their summed statistics give the first parameters (M-step, Sec. III-A).
3. EM on the voxels as weighted points (Verbeek, Nunnink & Vlassis 2006): a voxel's points
   share one responsibility, the E-step scores the voxel's mean and adds the trace of its
   scatter (em._e_step_block), the M-step sums its statistics. Each pass maximises a lower
   bound on the points' log-likelihood over M voxels instead of N points.
"""

from __future__ import annotations

import heapq

import numpy as np
from numba import njit

from gmm_core import em
from gmm_core.mixture import Mixture

# Voxel coordinates are packed into one int64 key, this many bits per axis (2^21 voxels along
# an axis: 100 km at 5 cm).
_KEY_BITS = 21
_FIBONACCI_HASH = np.uint64(0x9E3779B97F4A7C15)
# Power iterations for a group's principal axis: the cut needs a good direction, not an exact one.
_AXIS_ITERATIONS = 8


@njit(cache=True)
def _key_origin(points, size):
    """The smallest voxel index floor(x / size) along each axis, so that keys are non-negative."""
    n, d = points.shape
    lo = np.zeros(d, dtype=np.int64)
    hi = np.zeros(d, dtype=np.int64)
    for a in range(d):
        lo[a] = hi[a] = int(np.floor(points[0, a] / size))
    for i in range(n):
        for a in range(d):
            c = int(np.floor(points[i, a] / size))
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    for a in range(d):
        if hi[a] - lo[a] >= 2**_KEY_BITS:
            raise ValueError("voxels: the points span more voxels than a key holds")
    return lo


@njit(cache=True, inline="always")
def _voxel_key(points, i, origin, size):
    """Voxel floor(x_i / size) - origin packed into one int64."""
    key = 0
    for a in range(points.shape[1]):
        key = (key << _KEY_BITS) + (int(np.floor(points[i, a] / size)) - origin[a])
    return key


@njit(cache=True)
def _hash_table(n):
    """An open-addressing table for up to n keys: (keys, -1 where empty; shift of the hash)."""
    bits = 4
    while (1 << bits) < 2 * n:
        bits += 1
    return np.full(1 << bits, -1, dtype=np.int64), np.uint64(64 - bits)


@njit(cache=True, inline="always")
def _slot(table, shift, key):
    """The slot of `key` in `table`: where it is, or the empty slot where it goes (linear probing)."""
    h = np.int64((np.uint64(key) * _FIBONACCI_HASH) >> shift)
    while table[h] != -1 and table[h] != key:
        h = (h + 1) & (table.shape[0] - 1)
    return h


@njit(cache=True)
def count_voxels(points, size):
    """How many voxels floor(x / size) the (n, d) points occupy (np.unique of them, in one pass)."""
    if points.shape[0] == 0:
        return 0
    origin = _key_origin(points, size)
    table, shift = _hash_table(points.shape[0])
    count = 0
    last = -1
    for i in range(points.shape[0]):
        key = _voxel_key(points, i, origin, size)
        if key != last:
            h = _slot(table, shift, key)
            if table[h] == -1:
                table[h] = key
                count += 1
            last = key
    return count


@njit(cache=True)
def _voxel_statistics(points, voxel_size):
    """Per occupied voxel floor(x / voxel_size), the sums of em._features over its points (M, f),
    voxels in the order of their first point.

    A run of points in one voxel (a scan line crossing it) is summed in `run` and added to the
    voxel's row once, so the hash table is probed once per run, not once per point.
    """
    n, d = points.shape
    origin = _key_origin(points, voxel_size)
    table, shift = _hash_table(n)
    voxel_of_slot = np.empty(table.shape[0], dtype=np.int64)
    n_features = 1 + d + d * (d + 1) // 2
    sums = np.empty((n, n_features))
    run = np.zeros(n_features)
    n_voxels = 0
    run_key = -1
    for i in range(n + 1):
        key = _voxel_key(points, i, origin, voxel_size) if i < n else -2  # -2: past the end
        if key != run_key and run_key != -1:
            h = _slot(table, shift, run_key)
            if table[h] == -1:
                table[h] = run_key
                voxel_of_slot[h] = n_voxels
                sums[n_voxels] = 0.0
                n_voxels += 1
            for q in range(n_features):
                sums[voxel_of_slot[h], q] += run[q]
            run[:] = 0.0
        if i == n:
            break
        run_key = key
        run[0] += 1.0
        j = 1 + d
        for a in range(d):
            run[1 + a] += points[i, a]
            for b in range(a, d):
                run[j] += points[i, a] * points[i, b]
                j += 1
    return sums[:n_voxels].copy()


@njit(cache=True)
def _means_and_scatter(sums):
    """Each group's mean and its scatter (covariance of its points, upper triangle) from its sums."""
    m, f = sums.shape
    d = 3 if f == 10 else 2
    means = np.empty((m, d))
    scatter = np.empty((m, d * (d + 1) // 2))
    for v in range(m):
        n = sums[v, 0]
        for a in range(d):
            means[v, a] = sums[v, 1 + a] / n
        j = 1 + d
        for a in range(d):
            for b in range(a, d):
                s = sums[v, j] / n - means[v, a] * means[v, b]
                scatter[v, j - 1 - d] = max(s, 0.0) if a == b else s
                j += 1
    return means, scatter


@njit(cache=True)
def _spread(group_sums, d):
    """Sum of squared distances of a group's points to their mean: trace(sum x x^T) - |sum x|^2 / n."""
    n = group_sums[0]
    s = 0.0
    j = 1 + d
    for a in range(d):
        s += group_sums[j] - group_sums[1 + a] ** 2 / n
        j += d - a
    return s


@njit(cache=True)
def _principal_axis(group_sums, d, cov, axis, product):
    """The direction of largest variance of a group into `axis`, by power iteration from its widest
    axis (`cov`, `product`: (d, d) and (d,) scratch)."""
    n = group_sums[0]
    j = 1 + d
    for a in range(d):
        for b in range(a, d):
            c = group_sums[j] / n - group_sums[1 + a] * group_sums[1 + b] / (n * n)
            cov[a, b] = c
            cov[b, a] = c
            j += 1
    widest = 0
    for a in range(d):
        axis[a] = 0.0
        if cov[a, a] > cov[widest, widest]:
            widest = a
    axis[widest] = 1.0
    for _ in range(_AXIS_ITERATIONS):
        norm = 0.0
        for a in range(d):
            product[a] = 0.0
            for b in range(d):
                product[a] += cov[a, b] * axis[b]
            norm += product[a] * product[a]
        if norm == 0.0:
            break
        for a in range(d):
            axis[a] = product[a] / np.sqrt(norm)


@njit(cache=True)
def _split_groups(means, sums, n_groups):
    """Top-down partition of the voxels (rows of `means`, `sums`) into at most `n_groups` groups.

    The group of largest spread is cut at its mean across its principal axis, voxels whole, until
    there are `n_groups` groups or none can be cut (one voxel, or all of its voxels' means on one
    side). Returns the summed statistics of each group (G, f).
    """
    m, d = means.shape
    order = np.arange(m)
    first = np.empty(n_groups, dtype=np.int64)
    last = np.empty(n_groups, dtype=np.int64)
    group_sums = np.empty((n_groups, sums.shape[1]))
    first[0], last[0] = 0, m
    group_sums[0] = sums.sum(axis=0)
    heap = [(-_spread(group_sums[0], d), 0)]
    count = 1
    left = np.empty(sums.shape[1])
    centre, axis, product, cov = np.empty(d), np.empty(d), np.empty(d), np.empty((d, d))
    while count < n_groups and len(heap) > 0:
        _, g = heapq.heappop(heap)
        _principal_axis(group_sums[g], d, cov, axis, product)
        for a in range(d):
            centre[a] = group_sums[g, 1 + a] / group_sums[g, 0]
        left[:] = 0.0
        i, j = first[g], last[g] - 1
        while i <= j:  # in place: voxels on the low side of the cut first
            v = order[i]
            side = 0.0
            for a in range(d):
                side += (means[v, a] - centre[a]) * axis[a]
            if side <= 0.0:
                for q in range(sums.shape[1]):
                    left[q] += sums[v, q]
                i += 1
            else:
                order[i], order[j] = order[j], v
                j -= 1
        if i == first[g] or i == last[g]:
            continue  # this group cannot be cut; it stays as it is
        first[count], last[count] = i, last[g]
        group_sums[count] = group_sums[g] - left
        last[g] = i
        group_sums[g] = left
        for h in (g, count):
            if last[h] - first[h] > 1:
                heapq.heappush(heap, (-_spread(group_sums[h], d), h))
        count += 1
    return group_sums[:count].copy()


def fit_mixture_voxels(
    points: np.ndarray,
    n_components: int,
    voxel_size: float,
    *,
    reg_covar: float = 1e-4,
    max_iter: int = 100,
    tol: float = 1e-3,
) -> Mixture:
    """A mixture of at most `n_components` Gaussians for (n, d) points, by EM on the statistics
    of voxels of size `voxel_size` (m) from a top-down split; `reg_covar`, `max_iter` and `tol`
    as in em.fit_mixture (tol bounds the change of the bound per point).

    Deterministic: no seed. Fewer components come back when fewer groups can be cut than asked
    (voxels are never cut: the voxels must be much smaller than the components).
    """
    points = em.checked_points(points, "fit_mixture_voxels")
    n, d = points.shape
    if n == 0:
        return Mixture.empty(d)
    shift = points.mean(axis=0)
    sums = _voxel_statistics(points - shift, float(voxel_size))
    means, scatter = _means_and_scatter(sums)
    group_sums = _split_groups(means, sums, int(min(max(n_components, 1), n)))
    k = group_sums.shape[0]
    weights, mu, covs = np.empty(k), np.empty((k, d)), np.empty((k, d, d))
    em._m_step(group_sums, float(reg_covar), weights, mu, covs)
    em._refine(means, sums, scatter, weights, mu, covs, float(reg_covar), int(max_iter), float(tol))
    keep = weights > 1e-12
    return Mixture(weights[keep] / weights[keep].sum(), mu[keep] + shift, covs[keep], n)
