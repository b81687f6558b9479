"""Eq. 11 and Eq. 12 in closed form; AUROC against scikit-learn."""

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from gmm_core.metrics import auroc, called_free, grid_auroc
from gmm_core.occupancy import FREE, OCCUPIED, UNKNOWN, classify, map_estimate


def test_map_estimate_closed_form():
    hits = np.array([0.0, 3.0, 0.0, 2.0])
    misses = np.array([0.0, 0.0, 5.0, 2.0])
    p = map_estimate(hits, misses, prior=0.2)
    assert np.allclose(p, [0.5, 3.2 / 3.4, 0.2 / 5.4, 0.5])
    assert p.dtype == np.float32
    with pytest.raises(ValueError, match="prior"):
        map_estimate(hits, misses, prior=0.0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(7,), (33, 65), (5, 9, 4)])
def test_map_estimate_matches_numpy(dtype, shape):
    """The cell-by-cell kernel gives the bits of numpy's float32 expression of Eq. 11."""
    rng = np.random.default_rng(sum(shape))
    hits = (rng.exponential(2.0, shape) * (rng.random(shape) < 0.6)).astype(dtype)
    misses = (rng.exponential(5.0, shape) * (rng.random(shape) < 0.7)).astype(dtype)
    for prior in (0.2, 1.0, 0.013):
        h, m = hits.astype(np.float32), misses.astype(np.float32)
        reference = (h + prior) / (h + m + 2 * prior)
        p = map_estimate(hits, misses, prior)
        assert p.dtype == np.float32 and p.shape == shape
        assert np.array_equal(p, reference)
    assert np.array_equal(map_estimate(hits.T, misses.T), map_estimate(hits, misses).T)  # not contiguous
    with pytest.raises(ValueError, match="misses"):
        map_estimate(hits, misses[:1])


def test_classify_dead_band():
    p = np.array([0.05, 0.2, 0.5, 0.8, 0.95])
    # sigma^2 = 0.09: thresholds (1 ± 0.8) / 2 = 0.1 and 0.9.
    assert classify(p, 0.09).tolist() == [FREE, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED]
    # sigma^2 = 0.25: no dead band beyond p = 0.5 itself, which stays unknown.
    assert classify(p, 0.25).tolist() == [FREE, FREE, UNKNOWN, OCCUPIED, OCCUPIED]
    with pytest.raises(ValueError, match="variance"):
        classify(p, 0.3)


def test_auroc_matches_scikit_learn_with_ties():
    rng = np.random.default_rng(0)
    labels = rng.random(5000) < 0.3
    scores = np.round(rng.random(5000) + 0.3 * labels, 2)  # rounding makes many ties
    assert np.isclose(auroc(scores, labels), roc_auc_score(labels, scores))


def test_grid_auroc_leaves_out_unobserved_cells():
    truth_h = np.array([2.0, 0.0, 0.0, 0.0])
    truth_m = np.array([0.0, 3.0, 0.0, 1.0])
    prob = np.array([0.9, 0.1, 0.99, 0.2])
    assert grid_auroc(prob, truth_h, truth_m) == 1.0


def test_called_free_counts_the_occupied_cells_below_the_free_threshold():
    prob = np.array([[0.05, 0.29, 0.31], [0.5, 0.95, 0.01]])
    occupied = np.array([[True, True, True], [True, True, False]])
    # sigma^2 = 0.21: free below (1 - 0.4) / 2 = 0.3; the free cell at 0.01 is not an occupied one
    assert called_free(prob, occupied, 0.21) == 2 / 5
    assert called_free(prob, occupied, 0.0) == 0.0  # no band: p = 0 alone is free
    rng = np.random.default_rng(5)
    prob, occupied = rng.random((6, 7, 8)), rng.random((6, 7, 8)) < 0.2
    assert called_free(prob, occupied, 0.09) == np.mean(classify(prob, 0.09)[occupied] == FREE)
    with pytest.raises(ValueError, match="occupied"):
        called_free(prob, occupied[:2], 0.21)
    with pytest.raises(ValueError, match="occupied"):
        called_free(prob, np.zeros_like(occupied), 0.21)
