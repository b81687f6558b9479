"""EM on voxel statistics (gmm_core.voxel_em) against plain references: numpy's voxel sums, the
E-step on the expanded points, and scikit-learn's GaussianMixture with the same K."""

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal
from sklearn.mixture import GaussianMixture

from gmm_core import FitConfig, em, fit_scan
from gmm_core.voxel_em import _means_and_scatter, _split_groups, _voxel_statistics, count_voxels, fit_mixture_voxels


def scan_like(rng, n=3000):
    """Points along lines (runs of neighbours, as scan lines give) over two walls and a floor."""
    t = np.sort(rng.uniform(0, 6, n))
    wall = rng.integers(0, 3, n)
    points = np.column_stack([t, rng.uniform(0, 3, n), rng.normal(0, 0.01, n)])
    points[wall == 1] = points[wall == 1][:, [0, 2, 1]]
    points[wall == 2] = points[wall == 2][:, [2, 0, 1]] + [4.0, 0.0, 0.0]
    return points


@pytest.mark.parametrize("dim", [2, 3])
def test_voxel_statistics_match_numpy(dim):
    rng = np.random.default_rng(0)
    points = np.repeat(rng.uniform(-3, 3, (400, dim)), rng.integers(1, 5, 400), axis=0)  # runs
    points = np.concatenate([points, rng.uniform(-3, 3, (300, dim))])
    sums = _voxel_statistics(points, 0.7)
    cells, first, inverse = np.unique(np.floor(points / 0.7), axis=0, return_index=True, return_inverse=True)
    expected = np.zeros((len(cells), sums.shape[1]))
    np.add.at(expected, inverse.ravel(), em._features(points))
    expected = expected[np.argsort(first)]  # voxels in the order of their first point
    assert np.allclose(sums, expected, rtol=1e-12, atol=1e-9)
    assert count_voxels(points, 0.7) == len(cells)
    assert count_voxels(points[:0], 0.7) == 0


def test_split_groups_partition_the_voxels():
    points = scan_like(np.random.default_rng(1))
    sums = _voxel_statistics(points, 0.1)
    means, _ = _means_and_scatter(sums)
    groups = _split_groups(means, sums, 60)
    assert len(groups) == 60
    assert np.allclose(groups.sum(axis=0), sums.sum(axis=0))
    assert (groups[:, 0] >= 1).all()
    # Voxels are never cut: at most one group per voxel.
    assert len(_split_groups(means[:5], sums[:5], 60)) == 5


def dense_e_step(points, features, scatter, weights, means, covs):
    """em._e_step_block with every component a candidate of every point: (sum of log p, stats)."""
    k, d = means.shape
    prec, precision, log_norm = np.empty((k, d, d)), np.empty((k if len(scatter) else 0, d, d)), np.empty(k)
    em._prepare(weights, means, covs, prec, log_norm, precision)
    start, items = np.array([0, k]), np.arange(k)
    stats = np.empty((k, features.shape[1]))
    cells = np.zeros(len(points), dtype=np.int64)
    args = (start, items, prec, precision, means, log_norm, stats)
    return em._e_step_block(points, features, scatter, cells, 0, len(points), *args), stats


def random_mixture(rng, k, d):
    a = rng.normal(size=(k, d, d)) * 0.3
    return rng.dirichlet(np.ones(k)), rng.uniform(-2, 2, (k, d)), a @ a.transpose(0, 2, 1) + 0.05 * np.eye(d)


@pytest.mark.parametrize("dim", [2, 3])
def test_grouped_e_step_is_the_e_step_of_the_expanded_points(dim):
    # Voxels of identical points: the E-step on the voxels' sums must give exactly the sums and
    # the log-likelihood of the E-step on every point.
    rng = np.random.default_rng(2)
    weights, means, covs = random_mixture(rng, 7, dim)
    distinct = rng.uniform(-3, 3, (50, dim))
    counts = rng.integers(1, 6, 50)
    expanded = np.repeat(distinct, counts, axis=0)
    sums = _voxel_statistics(expanded, 1e-5)  # one voxel per distinct point
    group_means, scatter = _means_and_scatter(sums)
    ll_grouped, stats_grouped = dense_e_step(group_means, sums, scatter, weights, means, covs)
    ll_points, stats_points = dense_e_step(
        expanded, em._features(expanded), np.empty((0, scatter.shape[1])), weights, means, covs
    )
    assert ll_grouped == pytest.approx(ll_points, rel=1e-9)
    assert np.allclose(stats_grouped, stats_points, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_grouped_e_step_gives_the_bound_of_shared_responsibilities(dim):
    # Voxels with spread: sum_v n_v logsumexp_k(log pi_k + mean over v's points of log N(x | k)),
    # computed point by point with scipy, and never above the points' log-likelihood.
    rng = np.random.default_rng(3)
    weights, means, covs = random_mixture(rng, 6, dim)
    points = rng.uniform(-3, 3, (2000, dim))
    sums = _voxel_statistics(points, 0.8)
    group_means, scatter = _means_and_scatter(sums)
    bound, stats = dense_e_step(group_means, sums, scatter, weights, means, covs)
    voxel = np.unique(np.floor(points / 0.8), axis=0, return_inverse=True)[1].ravel()
    log_n = np.stack([multivariate_normal(m, c).logpdf(points) for m, c in zip(means, covs)], axis=1)
    order = np.unique(voxel, return_index=True)[1].argsort()  # voxel ids in order of first point
    mean_log_n = np.stack([log_n[voxel == v].mean(axis=0) for v in np.unique(voxel)[order]])
    expected = np.sum(sums[:, 0] * logsumexp(np.log(weights) + mean_log_n, axis=1))
    assert bound == pytest.approx(expected, rel=1e-9)
    assert bound <= np.sum(logsumexp(np.log(weights) + log_n, axis=1))
    assert stats[:, 0].sum() == pytest.approx(len(points))


def test_fit_recovers_well_separated_clusters():
    rng = np.random.default_rng(4)
    centres = rng.uniform(-20, 20, (5, 3))
    points = np.concatenate([c + 0.3 * rng.standard_normal((2000, 3)) for c in centres])
    mix = fit_mixture_voxels(points, 5, 0.1, reg_covar=1e-6)
    for c in centres:
        nearest = np.linalg.norm(mix.means - c, axis=1).argmin()
        assert np.linalg.norm(mix.means[nearest] - c) < 0.05
        assert np.allclose(mix.covariances[nearest], 0.09 * np.eye(3), atol=0.02)
    assert np.allclose(mix.weights, 0.2, atol=0.01) and mix.support == len(points)


@pytest.mark.xfail(
    strict=True,
    reason="issue 15 open: 0.25 m voxels share one responsibility, so the fit is 0.12-0.25 nats/point below "
    "scikit-learn (Kurt3D -0.125 vs +0.111 here; docs/BENCHMARKS.md), more than 5 %",
)
@pytest.mark.parametrize(
    "scan", [("kurt3d", {}), ("octomap/scan.dat.bz2", {"origin": (0, 0, 0.49)})], ids=["kurt3d", "octomap"]
)
def test_fit_scan_log_likelihood_within_5_percent_of_scikit_learn(data_dir, scan):
    # The 3D defaults (voxel EM) on a seeded 6,000-point subsample of a real scan, K as the
    # defaults choose it (one component per occupied 1 m cell), against scikit-learn's EM on
    # the same points with the same K.
    from services.datasets import read_scans

    path, options = scan
    hits = next(read_scans(data_dir / "3d" / path, **options)).hits
    points = hits[np.random.default_rng(0).choice(len(hits), 6000, replace=False)]
    ours = fit_scan(points, np.zeros((0, 3))).occupied
    k = FitConfig().for_dimension(3).n_components(points)
    assert ours.n_components == k
    theirs = GaussianMixture(k, covariance_type="full", reg_covar=1e-4, random_state=0).fit(points).score(points)
    ll = ours.log_density(points).mean()
    assert ll >= theirs - 0.05 * abs(theirs), (ll, theirs)


def test_fit_config_resolves_and_checks_the_voxel_fields():
    three, two = FitConfig().for_dimension(3), FitConfig().for_dimension(2)
    assert three.voxel_size > 0 and three.voxel_max_iter >= 1 and two.voxel_size == 0.0
    assert FitConfig(voxel_size=0.0).for_dimension(3).voxel_size == 0.0  # 3D EM on the points
    for bad in ({"voxel_size": -0.1}, {"voxel_size": float("nan")}, {"voxel_max_iter": 0}):
        with pytest.raises(ValueError, match="fit.voxel"):
            FitConfig(**bad)


def test_voxel_fit_of_degenerate_scans():
    for points in (np.zeros((0, 3)), np.array([[1.0, 2.0, 3.0]]), np.repeat([[3.0, -1.0, 2.0]], 10, axis=0)):
        mix = fit_scan(points, np.zeros((0, 3))).occupied
        assert mix.support == len(points) and mix.n_components == min(len(points), 1)
        assert (np.linalg.eigvalsh(mix.covariances) > 0).all()
