"""k-means in numba: the labels EM on points starts from (gmm_core.em)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _squared_distances(columns, x, out):
    """out[i] = |p_i - x|^2 for points stored as (d, n) columns, a loop numba vectorises."""
    out[:] = 0.0
    for a in range(columns.shape[0]):
        for i in range(columns.shape[1]):
            t = columns[a, i] - x[a]
            out[i] += t * t


@njit(cache=True)
def _kmeans_labels(points, n_clusters, seed, max_iter):
    """k-means++ seeding then Lloyd iterations, as scikit-learn initialises its EM.

    Seeded, so the same points always give the same mixture.
    """
    np.random.seed(seed)
    n, d = points.shape
    columns = np.ascontiguousarray(points.T)
    centres = np.empty((n_clusters, d))
    centres[0] = points[np.random.randint(n)]
    closest = np.empty(n)
    _squared_distances(columns, centres[0], closest)
    n_trials = 2 + int(np.log(n_clusters))
    candidate = np.empty(n)
    best_closest = np.empty(n)
    for k in range(1, n_clusters):
        # Greedy k-means++: draw a few seeds with probability proportional to D^2 and keep
        # the one that lowers the potential most (Arthur & Vassilvitskii; scikit-learn's rule).
        total = closest.sum()
        best_potential = np.inf
        for _ in range(n_trials):
            target = np.random.random() * total
            pick, acc = n - 1, 0.0
            for i in range(n):
                acc += closest[i]
                if acc >= target:
                    pick = i
                    break
            _squared_distances(columns, points[pick], candidate)
            potential = 0.0
            for i in range(n):
                candidate[i] = min(closest[i], candidate[i])
                potential += candidate[i]
            if potential < best_potential:
                best_potential = potential
                centres[k] = points[pick]
                best_closest[:] = candidate
        closest[:] = best_closest
    labels = np.zeros(n, dtype=np.int64)
    previous = np.empty(n, dtype=np.int64)
    nearest = np.empty(n)
    distance = np.empty(n)
    counts = np.zeros(n_clusters)
    for it in range(max_iter):
        # Assignment one centre at a time over all points, so the inner loop is contiguous.
        previous[:] = labels
        nearest[:] = np.inf
        for k in range(n_clusters):
            _squared_distances(columns, centres[k], distance)
            for i in range(n):
                if distance[i] < nearest[i]:
                    nearest[i] = distance[i]
                    labels[i] = k
        if it > 0 and (labels == previous).all():
            break
        centres[:] = 0.0
        counts[:] = 0.0
        for i in range(n):
            counts[labels[i]] += 1.0
            centres[labels[i]] += points[i]
        for k in range(n_clusters):
            if counts[k] > 0:
                centres[k] /= counts[k]
    return labels
