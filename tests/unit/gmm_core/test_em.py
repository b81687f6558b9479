"""The numba EM against scikit-learn and its E-step against the dense one, and its behaviour on
degenerate point sets."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal
from sklearn.mixture import GaussianMixture

from gmm_core import FitConfig, em, fit_scan
from gmm_core.em import fit_mixture
from gmm_core.hash_grid import _candidates, _cell_of, _hash_grid


def test_mean_log_likelihood_matches_scikit_learn_on_intel_scans(intel_scans):
    # Same data, same K (3 points per component), same variance floor; averaged over 40 scans
    # because either EM may land in a slightly different local optimum on any one scan.
    ours, theirs = [], []
    for scan in intel_scans[::23]:
        k = FitConfig().n_components(scan.hits)
        ours.append(fit_mixture(scan.hits, k, reg_covar=1e-4).log_density(scan.hits).mean())
        sk = GaussianMixture(k, covariance_type="full", reg_covar=1e-4, random_state=0).fit(scan.hits)
        theirs.append(sk.score(scan.hits))
    ours, theirs = np.mean(ours), np.mean(theirs)
    assert abs(ours - theirs) <= 0.01 * abs(theirs), (ours, theirs)


def test_mean_log_likelihood_matches_scikit_learn_on_kurt3d_scans(data_dir):
    # The 3D path: EM on a 1,600-point subset, then incremental-EM passes over all 8,000 points.
    # Either EM's log-likelihood moves by about 0.04 nats/point from one seed to the next on one
    # scan, so ours is averaged over four seeds; skipping the full-data passes costs 0.1.
    from services.datasets import read_scans

    ours, theirs = [], []
    for scan in read_scans(data_dir / "3d" / "kurt3d"):
        points = scan.hits[np.random.default_rng(0).choice(len(scan.hits), 8000, replace=False)]
        ours.append(np.mean([fit_mixture(points, 40, seed=s).log_density(points).mean() for s in range(4)]))
        sk = GaussianMixture(40, covariance_type="full", reg_covar=1e-4, random_state=0).fit(points)
        theirs.append(sk.score(points))
    ours, theirs = np.mean(ours), np.mean(theirs)
    assert ours >= theirs - 0.01 * abs(theirs), (ours, theirs)


def test_a_second_k_means_start_raises_the_log_likelihood(data_dir):
    # The OctoMap scan is where one start fell short of scikit-learn (docs/BENCHMARKS.md): keeping
    # the more likely of two starts must lift the mean over seeds (by 0.037 nats/point here, where
    # the seed-to-seed standard error of the mean is about 0.01).
    from services.datasets import read_scans

    scan = next(read_scans(data_dir / "3d" / "octomap" / "scan.dat.bz2", origin=(0, 0, 0.49)))
    points = scan.hits[np.random.default_rng(0).choice(len(scan.hits), 8000, replace=False)]
    one, two = (
        [fit_mixture(points, 40, seed=s, n_init=n).log_density(points).mean() for s in range(8)] for n in (1, 2)
    )
    assert np.mean(two) > np.mean(one) + 0.02, (np.mean(one), np.mean(two))


@pytest.mark.parametrize("dim", [2, 3])
def test_sparse_e_step_matches_the_dense_one(dim):
    # The E-step scores a point only against the components whose 5-sigma box reaches its hash
    # cell and drops responsibilities below e^-20; its sums must equal the plain dense E-step's.
    rng = np.random.default_rng(5)
    points = rng.uniform(-10, 10, (4000, dim)) * ([1.0, 0.3, 0.05][:dim])
    mix = fit_mixture(points, 80)
    weights, means, covs = mix.weights, mix.means, mix.covariances
    k = len(weights)
    lo, cell, dims = _hash_grid(points, k, len(points))
    cells = np.array([_cell_of(points, i, lo, cell, dims) for i in range(len(points))])
    order = np.argsort(cells, kind="stable")
    x, cells = points[order], cells[order]
    features = em._features(x)
    prec, log_norm = np.empty((k, dim, dim)), np.empty(k)
    em._prepare(weights, means, covs, prec, log_norm)
    start, items = _candidates(weights, means, covs, lo, cell, dims, 5.0)
    assert (np.diff(start)[cells] < k).all()  # the grid does prune
    stats = np.empty((k, features.shape[1]))
    ll = em._e_step_block(x, features, cells, 0, len(x), start, items, prec, means, log_norm, stats)

    log_comp = np.stack([np.log(w) + multivariate_normal(m, c).logpdf(x) for w, m, c in zip(weights, means, covs)])
    top = log_comp.max(axis=0)
    resp = np.exp(log_comp - top)
    dense_ll = np.sum(top + np.log(resp.sum(axis=0)))
    resp /= resp.sum(axis=0)
    assert ll == pytest.approx(dense_ll, rel=1e-6)
    # The responsibility left out of any point's candidates is below 1e-4 of that point.
    assert (np.abs(stats - resp @ features) <= 1e-4 * (resp @ np.abs(features)) + 1e-12).all()


@pytest.mark.parametrize("dim", [2, 3])
def test_recovers_well_separated_clusters(dim):
    rng = np.random.default_rng(1)
    centres = rng.uniform(-20, 20, (5, dim))
    points = np.concatenate([c + 0.3 * rng.standard_normal((400, dim)) for c in centres])
    mix = fit_mixture(points, 5, reg_covar=1e-6)
    for c in centres:
        nearest = np.linalg.norm(mix.means - c, axis=1).argmin()
        assert np.linalg.norm(mix.means[nearest] - c) < 0.1
        assert np.allclose(mix.covariances[nearest], 0.09 * np.eye(dim), atol=0.03)
    assert np.allclose(mix.weights, 0.2, atol=0.01)


@pytest.mark.parametrize(
    "points",
    [
        np.array([[1.0, 2.0]]),
        np.array([[1.0, 2.0], [1.5, 2.5]]),
        np.repeat([[3.0, -1.0, 2.0]], 10, axis=0),
        np.column_stack([np.linspace(0, 5, 30), 2 * np.linspace(0, 5, 30)]),  # collinear
        np.column_stack([np.linspace(0, 5, 30), np.zeros(30), np.zeros(30)]),
    ],
    ids=["one", "two", "duplicates", "collinear-2d", "collinear-3d"],
)
def test_degenerate_points_give_positive_definite_covariances(points):
    mix = fit_mixture(points, max(1, len(points) // 3))
    assert mix.n_components >= 1
    assert np.isfinite(mix.means).all() and np.isfinite(mix.covariances).all()
    assert (np.linalg.eigvalsh(mix.covariances) > 0).all()
    assert np.isclose(mix.weights.sum(), 1.0)
    assert mix.support == len(points)


def test_fit_is_deterministic_and_seeded():
    rng = np.random.default_rng(2)
    points = rng.standard_normal((500, 3)) * [4, 4, 0.1]
    a, b = fit_mixture(points, 20, seed=7), fit_mixture(points, 20, seed=7)
    assert np.array_equal(a.means, b.means) and np.array_equal(a.covariances, b.covariances)


def test_fit_scan_uses_free_beams_at_max_range():
    hits = np.array([[2.0, 0.1], [2.0, 0.0], [2.0, -0.1]])
    angles = np.linspace(1.0, 1.5, 12)
    no_return = np.column_stack([np.cos(angles), np.sin(angles)])
    model = fit_scan(hits, no_return, FitConfig(max_range=7.0))
    assert model.occupied.support == 3 and model.free.support == 12
    assert model.free.n_components == 4
    assert np.allclose(np.linalg.norm(model.free.means, axis=1), 7.0, atol=0.05)
    assert np.array_equal(model.origin, [0.0, 0.0])


def test_component_count_follows_points_and_component_size():
    rng = np.random.default_rng(3)
    patch = rng.uniform(0, 1, (3000, 3)) * [2.0, 2.0, 0.01]  # a 2 m x 2 m patch of surface
    assert FitConfig(points_per_component=3.0).n_components(patch) == 1000
    assert FitConfig().n_components(patch) == 100  # 3D: at least 30 points a component
    assert FitConfig().n_components(patch[:, :2]) == 1000  # 2D: 3 points a component
    assert FitConfig(component_size=0.5).n_components(patch) == 16
    assert FitConfig(component_size=0.5, max_components=10).n_components(patch) == 10


def test_fit_scan_of_an_empty_scan_is_empty():
    model = fit_scan(np.zeros((0, 2)), np.zeros((0, 2)))
    assert model.occupied.n_components == 0 and model.free.n_components == 0


def test_nan_points_are_rejected():
    with pytest.raises(ValueError, match="NaN"):
        fit_mixture(np.array([[0.0, np.nan], [1.0, 1.0]]), 1)
