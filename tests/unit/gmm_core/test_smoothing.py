"""The neighbourhood's prior of Eq. 11 (gmm_core.smoothing, occupancy.monte_carlo_estimate) against
its formula in numpy, the neighbourhood a plain padded convolution, on random grids."""

import numpy as np
import pytest

from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate, monte_carlo_estimate
from gmm_core.smoothing import NEIGHBOURHOOD_WEIGHT, PRIOR_BEAMS_AT_ONE, neighbourhood_estimate, prior_beams


def reference(counts: np.ndarray, c: float) -> np.ndarray:
    """[c, 1 - 2c, c] along each axis with the edge cells repeated outside, by padding."""
    out = counts.astype(np.float64)
    for axis in range(out.ndim):
        padded = np.pad(out, [(1, 1) if a == axis else (0, 0) for a in range(out.ndim)], mode="edge")
        left = np.take(padded, np.arange(0, out.shape[axis]), axis=axis)
        right = np.take(padded, np.arange(2, out.shape[axis] + 2), axis=axis)
        out = (1.0 - 2.0 * c) * out + c * (left + right)
    return out


def neighbourhood_reference(hits, misses, n0, prior=DEFAULT_PRIOR):
    c = NEIGHBOURHOOD_WEIGHT
    around_h, around_m = reference(hits, c), reference(misses, c)
    p_nb = (around_h + prior) / (around_h + around_m + 2 * prior)
    return (hits + n0 * p_nb + prior) / (hits + misses + n0 + 2 * prior)


@pytest.mark.parametrize("shape", [(7, 5, 3), (1, 9, 4), (6, 1, 1), (2, 1, 5), (1, 1, 1), (3, 40, 33)])
def test_neighbourhood_estimate_matches_the_padded_convolution(shape):
    rng = np.random.default_rng(sum(shape))
    hits, misses = rng.exponential(size=(2, *shape)) * rng.choice([0.0, 1.0, 30.0], size=(2, *shape))
    before = hits.copy(), misses.copy()
    for n0 in (0.0, 4.0, 53.0):
        got = neighbourhood_estimate(hits, misses, n0, DEFAULT_PRIOR)
        assert got.dtype == np.float32 and got.shape == shape
        np.testing.assert_allclose(got, neighbourhood_reference(hits, misses, n0), rtol=1e-6)
    assert np.array_equal(hits, before[0]) and np.array_equal(misses, before[1])  # the counts are left alone
    view = (slice(None), slice(None, None, -1), slice(None, None, 2))  # a strided window, float32 hits
    got = neighbourhood_estimate(hits[view].astype(np.float32), misses[view], 4.0, DEFAULT_PRIOR)
    np.testing.assert_allclose(
        got, neighbourhood_reference(hits[view].astype(np.float32), misses[view], 4.0), rtol=1e-6
    )


def test_a_constant_field_keeps_its_estimate_and_a_spike_reaches_its_26_neighbours_only():
    hits, misses = np.full((5, 6, 7), 2.5), np.full((5, 6, 7), 7.5)
    plain = map_estimate(hits, misses)
    np.testing.assert_allclose(neighbourhood_estimate(hits, misses, 16.0, DEFAULT_PRIOR), plain, rtol=1e-6)
    hits[2, 3, 3] = 1000.0
    changed = neighbourhood_estimate(hits, misses, 16.0, DEFAULT_PRIOR) != map_estimate(hits, misses)
    assert changed[1:4, 2:5, 2:5].all() and np.count_nonzero(changed) == 27


def test_counts_that_are_not_3d_are_refused_by_name():
    with pytest.raises(ValueError, match="hits, misses"):
        neighbourhood_estimate(np.zeros((3, 3)), np.zeros((3, 3)), 1.0, DEFAULT_PRIOR)
    with pytest.raises(ValueError, match="hits, misses"):
        neighbourhood_estimate(np.zeros((3, 3, 3)), np.zeros((3, 3, 2)), 1.0, DEFAULT_PRIOR)


def test_the_prior_weakens_with_the_samples_and_is_3d_only():
    assert prior_beams(1.0, 3) == PRIOR_BEAMS_AT_ONE
    assert prior_beams(4.0, 3) == PRIOR_BEAMS_AT_ONE / 4
    assert prior_beams(0.3, 2) == prior_beams(4.0, 2) == 0.0


def test_monte_carlo_estimate_takes_a_3d_cells_prior_from_its_neighbourhood_and_leaves_2d_alone():
    rng = np.random.default_rng(3)
    hits, misses = rng.exponential(size=(2, 6, 7, 8)) * rng.choice([0.0, 1.0, 100.0], size=(2, 6, 7, 8))
    for spc in (0.3, 1.0, 4.0):
        got = monte_carlo_estimate(hits.astype(np.float32), misses, spc)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, neighbourhood_reference(hits, misses, prior_beams(spc, 3)), rtol=1e-6)
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
