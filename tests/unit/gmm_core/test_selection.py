"""Order statistics of gmm_core.selection against numpy's on random arrays, ties included."""

import numpy as np
import pytest

from gmm_core.selection import kth_smallest, median


@pytest.mark.parametrize("levels", [None, 3, 1])  # distinct values, a few repeated, all equal
def test_kth_smallest_and_median_match_numpy(levels):
    rng = np.random.default_rng(levels or 0)
    for n in (1, 2, 3, 10, 101, 1000):
        values = rng.normal(size=n) if levels is None else rng.integers(0, levels, n).astype(np.float64)
        for k in {0, n // 3, n // 2, n - 1}:
            reordered = values.copy()
            assert kth_smallest(reordered, k) == np.partition(values, k)[k]
            assert np.all(reordered[:k] <= reordered[k]) and np.all(reordered[k + 1 :] >= reordered[k])
            assert np.array_equal(np.sort(reordered), np.sort(values))
        assert median(values.copy()) == np.median(values)
