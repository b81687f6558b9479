"""The sampling plan kernel (counts, offsets, weights per component) against its numpy reference, and
the quasi-random samples' spread."""

import numpy as np
import pytest
from scipy.stats import kstest

from gmm_core import Mixture
from gmm_core.sampling import WEIGHT_QUANTUM, MixtureSampler, _counts, _plan, draw, mixture_samples


@pytest.mark.parametrize("dim", [2, 3])
def test_the_plan_kernel_equals_the_numpy_rules_bit_for_bit(dim):
    rng = np.random.default_rng(dim)
    for trial in range(50):
        k = int(rng.integers(1, 200))
        sigmas = rng.uniform(0.0, 1.5, (k, dim)) ** 2
        expected = rng.uniform(0.1, 400.0, k) * (rng.random(k) < 0.9)  # some components hold no points
        resolution = float(rng.choice([0.01, 0.05, 0.1, 0.2, 0.37]))
        spc = float(rng.choice([0.5, 1.0, 4.0, 16.0]))
        counts, offsets, weights = _plan(sigmas, expected, resolution, spc)
        reference = _counts(sigmas, expected, resolution, spc)
        assert np.array_equal(counts, reference), f"trial {trial}"
        assert np.array_equal(offsets, np.cumsum(reference) - reference)
        assert np.array_equal(weights, np.round(expected / np.maximum(reference, 1) / WEIGHT_QUANTUM) * WEIGHT_QUANTUM)
        sampler = MixtureSampler(np.zeros((k, dim)), np.zeros((k, dim, dim)), sigmas, expected)
        same = sampler.samples(reference, np.uint64(7))
        fast = sampler.at(resolution, spc, np.uint64(7))
        for a, b in zip((same.counts, same.offsets, same.weights), (fast.counts, fast.offsets, fast.weights)):
            assert np.array_equal(a, b)


def test_a_component_s_samples_cover_its_gaussian_more_evenly_than_independent_draws():
    """Quasi-Monte-Carlo: 1,000 samples of one standard component lie within 0.01 of the normal
    distribution along each axis (Kolmogorov-Smirnov distance; 0.027 is typical of independent
    draws and 0.05 their 1 % tail), and over many streams the samples are unbiased."""
    for dim in (2, 3):
        unit = Mixture(np.ones(1), np.zeros((1, dim)), np.eye(dim)[None], 1000)
        for key in (1, 2, 3):
            points, _ = draw(mixture_samples(unit, np.array([1000]), np.uint64(key)))
            assert max(kstest(points[:, a], "norm").statistic for a in range(dim)) < 0.01
        firsts = np.stack([draw(mixture_samples(unit, np.array([2]), np.uint64(key)))[0] for key in range(2000)])
        assert np.all(np.abs(firsts.mean(axis=0)) < 5 / np.sqrt(2000))  # each sample is N(0, I): 5 standard errors
