"""gmm_core.smoothing against a plain numpy convolution on random grids, and the weights' rule."""

import numpy as np
import pytest

from gmm_core.occupancy import map_estimate, monte_carlo_estimate
from gmm_core.smoothing import MAX_SMOOTHING, SMOOTHING_AT_ONE, smoothed, smoothing_weight


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
    for c in (0.0, 0.05, MAX_SMOOTHING, 1.0 / 3.0):
        counts = rng.exponential(size=shape).astype(np.float32)
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


def test_the_weight_falls_with_the_samples_and_is_3d_only():
    assert smoothing_weight(1.0, 3) == SMOOTHING_AT_ONE
    assert smoothing_weight(4.0, 3) == pytest.approx(SMOOTHING_AT_ONE / 2)
    assert smoothing_weight(0.1, 3) == MAX_SMOOTHING
    assert smoothing_weight(0.1, 2) == smoothing_weight(4.0, 2) == 0.0


def test_monte_carlo_estimate_smooths_3d_counts_and_leaves_2d_ones():
    rng = np.random.default_rng(3)
    hits, misses = rng.exponential(size=(2, 6, 7, 8))
    c = smoothing_weight(2.0, 3)
    expected = map_estimate(reference(hits, c), reference(misses, c))
    np.testing.assert_allclose(monte_carlo_estimate(hits, misses, 2.0), expected, rtol=1e-6)
    assert np.array_equal(monte_carlo_estimate(hits[0], misses[0], 2.0), map_estimate(hits[0], misses[0]))
