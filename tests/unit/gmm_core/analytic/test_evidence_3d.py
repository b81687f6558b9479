"""gmm_core.analytic.evidence_3d against closed forms, scipy quadrature (Eq. 8) and Monte Carlo of the
ray-tracer's counting rule (a ray that crosses a cube and ends outside it is a miss, its misses
stopped short of the sample (hit_stop); a sample inside is a hit, or a miss for a
max-range component)."""

import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from gmm_core.analytic.cells import component_evidence
from gmm_core.analytic.evidence_3d import edge_piece_eq8
from support.evidence import hit_stop, monte_carlo


def random_rotation_3d(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_edge_integral_eq8_is_the_closed_form_of_the_approximated_integrand():
    rng = np.random.default_rng(3)

    def erf_hat(x):  # Eq. 7
        return np.sign(x) * (1 - np.exp(-2 / np.pi * np.abs(x) * (np.abs(x) + np.sqrt(np.pi))))

    def approximated_integrand(x, x0, y0, slope):  # Eq. 8's integrand along the edge y = y0 + slope (x - x0)
        return math.exp(-x * x / 2) * erf_hat((y0 + slope * (x - x0)) / math.sqrt(2))

    assert np.abs(erf_hat(np.linspace(-5, 5, 10001)) - special.erf(np.linspace(-5, 5, 10001))).max() < 0.0141
    for _ in range(100):
        x0, x1 = rng.normal(0, 2, 2)
        slope = rng.normal() * 10 ** rng.uniform(-1, 4)  # up to nearly vertical edges
        y0 = rng.normal(0, 2)
        y1 = y0 + slope * (x1 - x0)
        if y0 * y1 < 0:
            continue  # Eq. 9 splits such edges at y = 0
        sign = 1.0 if y0 + y1 >= 0 else -1.0
        # A steep edge saturates e_hat within 3/slope of its y = 0 end: tell quad where.
        bends = [x0 + (sign * y - y0) / slope for y in (0.1, 0.3, 1.0, 3.0, 10.0)]
        bends = [x for x in bends if min(x0, x1) < x < max(x0, x1)] or None
        reference = integrate.quad(
            approximated_integrand, x0, x1, args=(x0, y0, slope), points=bends, epsabs=1e-13, epsrel=1e-12, limit=400
        )[0]
        got = edge_piece_eq8(x0, y0, x1, y1, sign)
        assert got == pytest.approx(reference, abs=1e-11)


def random_case_3d(rng, kind):
    rot = random_rotation_3d(rng)
    sd = np.sort(10 ** rng.uniform(-2, -0.6, 3))
    if kind == 4:
        sd[0] = 1e-6  # a nearly degenerate (flat) component
    cov = rot @ np.diag(sd**2) @ rot.T
    mean = rng.uniform(-2, 2, 3)
    origin = mean + rng.normal(0, 1, 3) * rng.uniform(0.5, 3)
    size = 10 ** rng.uniform(-1.3, -0.6)
    center = [
        mean + rot @ (rng.normal(0, 1, 3) * sd),
        origin + (mean - origin) * rng.uniform(0.3, 1.2) + rng.normal(0, 0.5, 3) * sd[-1],
        mean + rot @ (rng.normal(0, 3, 3) * sd),
        origin + rng.uniform(-0.5, 0.5, 3) * size,
        mean + rot @ (rng.normal(0, 1, 3) * sd),
    ][kind]
    return mean, cov, origin, center, size


def test_cube_mass_is_exact_for_an_axis_aligned_component():
    rng = np.random.default_rng(6)
    for _ in range(20):
        sd = 10 ** rng.uniform(-2.5, 0, 3)
        mean = rng.normal(0, 0.1, 3)
        center, size = rng.normal(0, 0.1, 3), 10 ** rng.uniform(-2, -0.5)
        lo, hi = (center - size / 2 - mean) / sd, (center + size / 2 - mean) / sd
        exact = np.prod(stats.norm.cdf(hi) - stats.norm.cdf(lo))
        hits, _ = component_evidence(mean, np.diag(sd**2), mean + 5, center[None], size)
        # Slices have constant shape here: only the Gauss-Legendre rule in Phi(z) errs.
        assert hits[0] == pytest.approx(exact, abs=1e-9)


@pytest.mark.parametrize("kind", [0, 1, 2, 3, 4], ids=["inside", "on-beam", "beside", "at-sensor", "flat"])
def test_3d_hits_and_misses_match_monte_carlo(kind):
    rng = np.random.default_rng(30 + kind)
    n = 300_000
    for _ in range(3):
        mean, cov, origin, center, size = random_case_3d(rng, kind)
        hits, misses = component_evidence(mean, cov, origin, center[None], size)
        _, misses_free = component_evidence(mean, cov, origin, center[None], size, max_range=True)
        # The cube that holds the sensor is crossed by every ray: the analytic evidence counts every
        # sample outside it, where the tracer leaves out those within the stop of the sensor, which a
        # range sensor does not return (evidence_3d.cell_evidence_3d).
        stop = 0.0 if kind == 3 else hit_stop(cov, size)
        mc_hits, mc_misses = monte_carlo(mean, cov, origin, center, size, n, rng, stop=stop)
        _, mc_free = monte_carlo(mean, cov, origin, center, size, n, rng, max_range=True)
        assert np.isfinite([hits[0], misses[0], misses_free[0]]).all()
        # Near the component both are exact up to quadrature; well in front of it misses use the
        # erf approximation of Eq. 9, good to 0.012 of the component's mass (see the polygon test).
        pairs = ((hits[0], mc_hits, 0.0), (misses[0], mc_misses, 0.012), (misses_free[0], mc_free, 0.012))
        for value, mc, slack in pairs:
            assert value == pytest.approx(mc, abs=5 * math.sqrt(mc * (1 - mc) / n) + 1e-4 + slack)


@pytest.mark.parametrize(
    "mean, thinnest",
    [([1.3, 1.1, 0.9], 0.03), ([1.9, 1.3, 0.7], 0.1)],
    ids=["near, stopped a cube short", "at 1 m, stopped 3 sigmas short"],
)
def test_3d_sensor_on_a_corner_shared_by_eight_cubes(mean, thinnest):
    # A component whose stop reaches back to the sensor's own cubes is where the analytic scaling
    # errs (evidence_3d.cell_evidence_3d): the first at 0.33 m with a 3-sigma stop of 0.3 m, 0.090.
    rng = np.random.default_rng(8)
    mean, cov = np.array(mean), np.diag([thinnest, 0.2, 0.1]) ** 2
    sensor = np.array([1.0, 1.0, 1.0])
    offsets = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)]) - 0.5
    centers = sensor + 0.1 * offsets  # with round-off, as a grid computes them
    hits, misses = component_evidence(mean, cov, sensor, centers, 0.1)
    assert misses[7] == pytest.approx(1 - hits[7], abs=1e-12)  # the upper cube holds the sensor
    for c, h, m in zip(centers[:7], hits[:7], misses[:7]):
        mc_h, mc_m = monte_carlo(mean, cov, sensor, c, 0.1, 200_000, rng, stop=hit_stop(cov, 0.1))
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=5e-3)


def test_3d_exact_slices_agree_with_monte_carlo_closely_near_the_component():
    """Cells straddling a tilted flat component: the exact path, held to Monte-Carlo noise alone."""
    rng = np.random.default_rng(7)
    n = 1_000_000
    rot = random_rotation_3d(rng)
    cov = rot @ np.diag([0.01, 0.1, 0.2]) ** 2 @ rot.T
    mean, origin = np.array([3.0, 0.5, 0.2]), np.zeros(3)
    centers = mean + np.array([[0.0, 0, 0], [0.03, 0.05, -0.02], [-0.06, 0.1, 0.1]])
    hits, misses = component_evidence(mean, cov, origin, centers, 0.1)
    for c, h, m in zip(centers, hits, misses):
        mc_h, mc_m = monte_carlo(mean, cov, origin, c, 0.1, n, rng, stop=hit_stop(cov, 0.1))
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=2e-3)  # > 4 standard deviations at 1e6
