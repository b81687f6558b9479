"""gmm_core.analytic.special against scipy quadrature."""

import math

import numpy as np
import pytest
from scipy import integrate, stats

from gmm_core.analytic.special import bvn_upper


def test_bivariate_normal_orthant_matches_quadrature():
    rng = np.random.default_rng(1)
    for _ in range(80):
        h, k = rng.normal(0, 2, 2)
        r = rng.uniform(-0.999, 0.999)
        reference = integrate.quad(
            lambda x, k, r: stats.norm.pdf(x) * stats.norm.sf((k - r * x) / math.sqrt(1 - r * r)),
            h,
            np.inf,
            args=(k, r),
            epsabs=1e-14,
            epsrel=1e-12,
        )[0]
        # Genz's algorithm is good to ~1e-15; quad to ~1e-12 here.
        assert bvn_upper(h, k, r) == pytest.approx(reference, abs=1e-10)
    # Fully correlated limits: one half-line, or the interval between the two bounds.
    assert bvn_upper(0.3, -0.2, 1.0) == pytest.approx(stats.norm.sf(0.3), abs=1e-15)
    between = stats.norm.cdf(0.2) - stats.norm.cdf(-0.3)
    assert bvn_upper(-0.3, -0.2, -1.0) == pytest.approx(between, abs=1e-15)
