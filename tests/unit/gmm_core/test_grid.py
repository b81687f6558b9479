"""The grid convention: a bad resolution is refused before any arithmetic with it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gmm_core import Grid


@pytest.mark.parametrize("resolution", [0.0, -0.1, float("nan"), float("inf")])
def test_a_bad_resolution_is_refused_without_a_numpy_warning(resolution):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning from dividing by it fails the test
        with pytest.raises(ValueError, match="^grid: resolution must be positive"):
            Grid.from_bbox([0.0, 0.0], [1.0, 1.0], resolution)
        with pytest.raises(ValueError, match="^grid: resolution must be positive"):
            Grid(np.zeros(2), resolution, (1, 1))
