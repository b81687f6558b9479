"""gmm_core.smoothing against a plain numpy convolution on random grids, and the neighbourhood's
prior of Eq. 11 (occupancy.monte_carlo_estimate) against its formula in numpy."""

import numpy as np
import pytest

from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate, monte_carlo_estimate
from gmm_core.smoothing import NEIGHBOURHOOD_WEIGHT, PRIOR_BEAMS_AT_ONE, prior_beams, smoothed


def reference(counts: np.ndarray, c: float) -> np.ndarray:
    """[c, 1 - 2c, c] along each axis with the edge cells repeated outside, by padding."""
    out = counts.astype(np.float64)
    for axis in range(out.ndim):
        padded = np.pad(out, [(1, 1) if a == axis else (0, 0) for a in range(out.ndim)], mode="edge")
        left = np.take(padded, np.arange(0, out.shape[axis]), axis=axis)
        right = np.take(padded, np.arange(2, out.shape[axis] + 2), axis=axis)
        out = (1.0 - 2.0 * c) * out + c * (left + right)
    return out


@pytest.mark.parametrize("shape", [(7, 5, 3), (1, 9, 4), (6, 1, 1), (2, 2), (11,), (3, 4, 5, 2)])
def test_smoothed_matches_the_padded_convolution(shape):
    rng = np.random.default_rng(len(shape) * 10 + shape[0])
    for c, dtype in zip((0.0, 0.05, NEIGHBOURHOOD_WEIGHT, 1.0 / 3.0), (np.float32, np.float64) * 2):
        counts = rng.exponential(size=shape).astype(dtype)
        before = counts.copy()
        out = smoothed(counts, c)
        assert out.dtype == np.float64 and out.shape == counts.shape
        np.testing.assert_allclose(out, reference(counts, c), rtol=1e-12, atol=1e-12)
        assert np.array_equal(counts, before)  # the input is left alone


def test_a_constant_field_stays_and_a_spike_spreads_to_its_neighbours_only():
    assert np.array_equal(smoothed(np.full((4, 5, 6), 2.5), 0.1), np.full((4, 5, 6), 2.5))
    spike = np.zeros((5, 5, 5))
    spike[2, 2, 2] = 1.0
    out = smoothed(spike, 0.1)
    assert out[2, 2, 2] == pytest.approx(0.8**3)
    assert out[1, 2, 2] == out[2, 3, 2] == pytest.approx(0.1 * 0.8**2)
    assert out.sum() == pytest.approx(1.0)  # far from the edges nothing is lost
    assert np.count_nonzero(out) == 27


def test_bad_weights_are_refused_by_name():
    with pytest.raises(ValueError, match="weight"):
        smoothed(np.zeros((3, 3, 3)), 0.4)
    with pytest.raises(ValueError, match="weight"):
        smoothed(np.zeros((3, 3, 3)), -0.01)


def test_the_prior_weakens_with_the_samples_and_is_3d_only():
    assert prior_beams(1.0, 3) == PRIOR_BEAMS_AT_ONE
    assert prior_beams(4.0, 3) == PRIOR_BEAMS_AT_ONE / 4
    assert prior_beams(0.3, 2) == prior_beams(4.0, 2) == 0.0


def neighbourhood_reference(hits, misses, samples_per_cell, prior=DEFAULT_PRIOR):
    n0, c = prior_beams(samples_per_cell, 3), NEIGHBOURHOOD_WEIGHT
    around_h, around_m = reference(hits, c), reference(misses, c)
    p_nb = (around_h + prior) / (around_h + around_m + 2 * prior)
    return (hits + n0 * p_nb + prior) / (hits + misses + n0 + 2 * prior)


def test_monte_carlo_estimate_takes_a_3d_cells_prior_from_its_neighbourhood_and_leaves_2d_alone():
    rng = np.random.default_rng(3)
    hits, misses = rng.exponential(size=(2, 6, 7, 8)) * rng.choice([0.0, 1.0, 100.0], size=(2, 6, 7, 8))
    for spc in (0.3, 1.0, 4.0):
        got = monte_carlo_estimate(hits.astype(np.float32), misses, spc)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, neighbourhood_reference(hits, misses, spc), rtol=1e-6)
    assert np.array_equal(monte_carlo_estimate(hits[0], misses[0], 2.0), map_estimate(hits[0], misses[0]))


def test_an_unseen_cell_takes_its_neighbourhoods_estimate_and_a_well_seen_one_keeps_its_own():
    hits, misses = np.zeros((5, 5, 5)), np.full((5, 5, 5), 50.0)  # free space all round ...
    misses[2, 2, 2] = 0.0  # ... but for one cell no ray reached
    hits[0, 0, 0], misses[0, 0, 0] = 1e4, 0.0  # and one, two cells away, seen occupied by many
    p = monte_carlo_estimate(hits, misses, 1.0)
    assert map_estimate(hits, misses)[2, 2, 2] == 0.5 and p[2, 2, 2] < 0.1
    assert p[0, 0, 0] > 0.99
    with pytest.raises(ValueError, match="misses"):
        monte_carlo_estimate(hits, misses[:4], 1.0)
    with pytest.raises(ValueError, match="prior"):
        monte_carlo_estimate(hits, misses, 1.0, prior=0.0)
