"""Mixtures, poses and Eq. 2 against plain references."""

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from gmm_core import Mixture, Pose


def random_mixture(rng, k, dim):
    a = rng.standard_normal((k, dim, dim))
    covs = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(dim)
    w = rng.uniform(0.5, 1.5, k)
    return Mixture(w / w.sum(), rng.uniform(-5, 5, (k, dim)), covs, 100)


def random_pose(rng, dim):
    if dim == 2:
        return Pose.from_xytheta(*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi))
    return Pose.from_quaternion(rng.uniform(-3, 3, 3), rng.standard_normal(4))


@pytest.mark.parametrize("dim", [2, 3])
def test_log_density_matches_scipy(dim):
    rng = np.random.default_rng(0)
    mix = random_mixture(rng, 4, dim)
    x = rng.uniform(-6, 6, (50, dim))
    ref = np.log(sum(w * multivariate_normal(m, c).pdf(x) for w, m, c in zip(mix.weights, mix.means, mix.covariances)))
    assert np.allclose(mix.log_density(x), ref)


@pytest.mark.parametrize("dim", [2, 3])
def test_transformed_mixture_matches_transformed_samples(dim):
    # Eq. 2 moves the density exactly as moving each sample moves it.
    rng = np.random.default_rng(1)
    mix = random_mixture(rng, 1, dim)
    pose = random_pose(rng, dim)
    samples = rng.multivariate_normal(mix.means[0], mix.covariances[0], 200_000)
    moved = pose.apply(samples)
    world = mix.transformed(pose)
    assert np.allclose(world.means[0], moved.mean(axis=0), atol=0.03)
    assert np.allclose(world.covariances[0], np.cov(moved.T), rtol=0.03, atol=0.03)


@pytest.mark.parametrize("dim", [2, 3])
def test_pose_compose_inverse_and_round_trips(dim):
    rng = np.random.default_rng(2)
    a, b = random_pose(rng, dim), random_pose(rng, dim)
    x = rng.standard_normal((5, dim))
    assert np.allclose(a.compose(b).apply(x), a.apply(b.apply(x)))
    assert np.allclose(a.inverse().apply(a.apply(x)), x)
    if dim == 2:
        assert np.allclose(Pose.from_xytheta(*a.as_xytheta()).R, a.R)
    else:
        q = a.as_quaternion()
        assert np.allclose(Pose.from_quaternion(a.t, q).R, a.R)


def test_pose_rejects_non_rotations():
    with pytest.raises(ValueError, match="rotation"):
        Pose(np.diag([1.0, -1.0]), np.zeros(2))
    with pytest.raises(ValueError, match="non-finite"):
        Pose(np.eye(2), np.array([np.nan, 0.0]))


def test_mixture_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="covariances"):
        Mixture(np.ones(2) / 2, np.zeros((2, 2)), np.zeros((2, 3, 3)), 10)
