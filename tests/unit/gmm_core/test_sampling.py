"""The sampling plan kernel (counts, offsets, weights per component) against its numpy reference."""

import numpy as np
import pytest

from gmm_core.sampling import WEIGHT_QUANTUM, MixtureSampler, _counts, _plan


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
