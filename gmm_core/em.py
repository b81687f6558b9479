"""Expectation-maximisation for a Gaussian mixture (Sec. III-A), in numba.

Initialised by seeded k-means++ and Lloyd iterations, like scikit-learn's GaussianMixture,
so the two reach the same kind of optimum; the E-step only visits the components whose
5-sigma box holds the point (a hash grid of component boxes), so a 3D scan with many
components costs a few component evaluations per point, not K.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from gmm_core.mixture import Mixture

_LOG_2PI = np.log(2.0 * np.pi)
# Responsibilities below exp(-30) change no sum in double precision that matters here.
_LOG_RESP_FLOOR = -30.0


@njit(cache=True)
def _squared_distance(points, i, centres, k):
    s = 0.0
    for a in range(points.shape[1]):
        t = points[i, a] - centres[k, a]
        s += t * t
    return s


@njit(cache=True)
def _kmeans_labels(points, n_clusters, seed, max_iter):
    """k-means++ seeding then Lloyd iterations, as scikit-learn initialises its EM.

    Seeded, so the same points always give the same mixture.
    """
    np.random.seed(seed)
    n, d = points.shape
    centres = np.empty((n_clusters, d))
    centres[0] = points[np.random.randint(n)]
    closest = np.empty(n)
    for i in range(n):
        closest[i] = _squared_distance(points, i, centres, 0)
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
            potential = 0.0
            for i in range(n):
                s = 0.0
                for a in range(d):
                    t = points[i, a] - points[pick, a]
                    s += t * t
                candidate[i] = min(closest[i], s)
                potential += candidate[i]
            if potential < best_potential:
                best_potential = potential
                centres[k] = points[pick]
                best_closest[:] = candidate
        closest[:] = best_closest
    labels = np.zeros(n, dtype=np.int64)
    counts = np.zeros(n_clusters)
    for it in range(max_iter):
        changed = 0
        for i in range(n):
            best, best_k = np.inf, 0
            for k in range(n_clusters):
                s = _squared_distance(points, i, centres, k)
                if s < best:
                    best, best_k = s, k
            if it == 0 or labels[i] != best_k:
                changed += 1
            labels[i] = best_k
        if changed == 0:
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


@njit(cache=True)
def _cholesky_inverse(cov, out):
    """Write L^{-1} (lower triangular) of cov = L L^T into `out`; return log det(cov)."""
    d = cov.shape[0]
    L = np.zeros((d, d))
    for j in range(d):
        s = cov[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, d):
            s = cov[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    log_det = 0.0
    for j in range(d):
        log_det += 2.0 * np.log(L[j, j])
    for j in range(d):
        out[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, d):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * out[k, j]
            out[i, j] = s / L[i, i]
        for i in range(j):
            out[i, j] = 0.0
    return log_det


@njit(cache=True)
def _m_step(n_k, sum_x, sum_xx, reg_covar, weights, means, covs):
    """Parameters from the sufficient statistics; reg_covar on the diagonal keeps them PD."""
    k_count, d = sum_x.shape
    total = 0.0
    for k in range(k_count):
        total += n_k[k]
    for k in range(k_count):
        nk = max(n_k[k], 1e-300)
        weights[k] = n_k[k] / total
        for a in range(d):
            means[k, a] = sum_x[k, a] / nk
        for a in range(d):
            for b in range(d):
                c = sum_xx[k, a, b] / nk - means[k, a] * means[k, b]
                covs[k, a, b] = c
        # Symmetrise and floor: a cancellation in E[xx]-mu mu^T must not give a negative variance.
        for a in range(d):
            for b in range(a + 1, d):
                c = 0.5 * (covs[k, a, b] + covs[k, b, a])
                covs[k, a, b] = c
                covs[k, b, a] = c
            covs[k, a, a] = max(covs[k, a, a], 0.0) + reg_covar


@njit(cache=True)
def _labels_statistics(points, labels, k_count):
    n, d = points.shape
    n_k = np.zeros(k_count)
    sum_x = np.zeros((k_count, d))
    sum_xx = np.zeros((k_count, d, d))
    for i in range(n):
        k = labels[i]
        n_k[k] += 1.0
        for a in range(d):
            sum_x[k, a] += points[i, a]
            for b in range(d):
                sum_xx[k, a, b] += points[i, a] * points[i, b]
    return n_k, sum_x, sum_xx


@njit(cache=True)
def _hash_grid(points, n_components):
    """A uniform grid over the points with about 2^d cells per component: (lo, cell size, dims)."""
    n, d = points.shape
    lo = np.empty(d)
    extent = np.empty(d)
    for a in range(d):
        lo[a] = points[:, a].min()
        extent[a] = points[:, a].max() - lo[a]
    per_axis = 4.0 * n_components ** (1.0 / d)
    cell = max(extent.max() / per_axis, 1e-9)
    dims = np.empty(d, dtype=np.int64)
    for a in range(d):
        dims[a] = max(1, min(int(extent[a] / cell) + 1, 256))
    return lo, cell, dims


@njit(cache=True)
def _cell_of(x, lo, cell, dims):
    flat = 0
    for a in range(dims.shape[0]):
        i = int((x[a] - lo[a]) / cell)
        i = min(max(i, 0), dims[a] - 1)
        flat = flat * dims[a] + i
    return flat


@njit(cache=True)
def _candidates(means, covs, lo, cell, dims):
    """CSR lists: for each hash cell, the components whose 5-sigma box overlaps it."""
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
            for a in range(d):
                half = 5.0 * np.sqrt(covs[k, a, a])
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


@njit(cache=True, inline="always")
def _mahalanobis(points, i, prec, means, k):
    """|L^{-1}(x_i - mu_k)|^2 with L^{-1} lower triangular, unrolled for d = 2 and 3."""
    x0 = points[i, 0] - means[k, 0]
    x1 = points[i, 1] - means[k, 1]
    y0 = prec[k, 0, 0] * x0
    y1 = prec[k, 1, 0] * x0 + prec[k, 1, 1] * x1
    if points.shape[1] == 2:
        return y0 * y0 + y1 * y1
    x2 = points[i, 2] - means[k, 2]
    y2 = prec[k, 2, 0] * x0 + prec[k, 2, 1] * x1 + prec[k, 2, 2] * x2
    return y0 * y0 + y1 * y1 + y2 * y2


@njit(cache=True)
def _e_step_statistics(points, point_cell, lo, cell, dims, weights, means, covs):
    """One E-step fused with the statistics of the next M-step; returns the mean log-likelihood.

    A point is scored against the components listed for its hash cell; one that no
    component's 5-sigma box reaches is scored against all of them.
    """
    n, d = points.shape
    k_count = weights.shape[0]
    prec = np.empty((k_count, d, d))
    log_norm = np.empty(k_count)
    for k in range(k_count):
        log_det = _cholesky_inverse(covs[k], prec[k])
        log_norm[k] = np.log(weights[k]) - 0.5 * (log_det + d * _LOG_2PI)
    start, items = _candidates(means, covs, lo, cell, dims)
    everyone = np.arange(k_count)
    n_k = np.zeros(k_count)
    sum_x = np.zeros((k_count, d))
    sum_xx = np.zeros((k_count, d, d))
    log_p = np.empty(k_count)
    total_ll = 0.0
    for i in range(n):
        c = point_cell[i]
        comps = items[start[c]:start[c + 1]] if start[c + 1] > start[c] else everyone
        best = -np.inf
        for j in range(comps.shape[0]):
            k = comps[j]
            log_p[j] = log_norm[k] - 0.5 * _mahalanobis(points, i, prec, means, k)
            best = max(best, log_p[j])
        norm = 0.0
        for j in range(comps.shape[0]):
            log_p[j] = np.exp(log_p[j] - best) if log_p[j] - best > _LOG_RESP_FLOOR else 0.0
            norm += log_p[j]
        total_ll += best + np.log(norm)
        for j in range(comps.shape[0]):
            r = log_p[j] / norm
            if r == 0.0:
                continue
            k = comps[j]
            n_k[k] += r
            for a in range(d):
                sum_x[k, a] += r * points[i, a]
                for b in range(d):
                    sum_xx[k, a, b] += r * points[i, a] * points[i, b]
    return total_ll / n, n_k, sum_x, sum_xx


@njit(cache=True)
def _refine(points, weights, means, covs, reg_covar, max_iter, tol):
    """EM iterations in place until the mean log-likelihood changes by less than `tol`."""
    n = points.shape[0]
    lo, cell, dims = _hash_grid(points, weights.shape[0])
    point_cell = np.empty(n, dtype=np.int64)
    for i in range(n):
        point_cell[i] = _cell_of(points[i], lo, cell, dims)
    previous = -np.inf
    for _ in range(max_iter):
        ll, n_k, sum_x, sum_xx = _e_step_statistics(points, point_cell, lo, cell, dims, weights, means, covs)
        _m_step(n_k, sum_x, sum_xx, reg_covar, weights, means, covs)
        if abs(ll - previous) < tol:
            break
        previous = ll


@njit(cache=True)
def _em(points, n_components, reg_covar, max_iter, tol, seed, init_points):
    """Coarse to fine: k-means and EM on a seeded subset, then EM on every point.

    `points` are centred so that second moments keep their precision.
    """
    n, d = points.shape
    np.random.seed(seed)
    subset = points[np.random.permutation(n)[:init_points]] if n > init_points else points
    labels = _kmeans_labels(subset, n_components, seed, 100)
    n_k, sum_x, sum_xx = _labels_statistics(subset, labels, n_components)
    weights = np.empty(n_components)
    means = np.empty((n_components, d))
    covs = np.empty((n_components, d, d))
    _m_step(n_k, sum_x, sum_xx, reg_covar, weights, means, covs)
    _refine(subset, weights, means, covs, reg_covar, max_iter, tol)
    if n > init_points:
        _refine(points, weights, means, covs, reg_covar, max_iter, tol)
    return weights, means, covs


def fit_mixture(points: np.ndarray, n_components: int, *, reg_covar: float = 1e-4,
                max_iter: int = 100, tol: float = 1e-3, seed: int = 0,
                init_points_per_component: float = 40.0) -> Mixture:
    """Maximum-likelihood mixture of `n_components` Gaussians for (n, d) points, by EM.

    `reg_covar` is added to every variance (as scikit-learn's reg_covar), so duplicate,
    collinear or single points still give positive-definite covariances. Components that
    end with no responsibility are dropped. `tol` bounds the change of the mean
    log-likelihood per point between iterations, as in scikit-learn.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"fit_mixture: points must be (n, 2|3), got {points.shape}")
    n, d = points.shape
    if n == 0:
        return Mixture.empty(d)
    if not np.isfinite(points).all():
        raise ValueError("fit_mixture: points contain NaN or inf")
    k = int(min(max(n_components, 1), n))
    shift = points.mean(axis=0)
    weights, means, covs = _em(points - shift, k, float(reg_covar), int(max_iter), float(tol),
                               int(seed), max(int(init_points_per_component * k), 1))
    keep = weights > 1e-12
    return Mixture(weights[keep] / weights[keep].sum(), means[keep] + shift, covs[keep], n)
