"""gmm_core.analytic.evidence_2d against references: scipy quadrature of the defining integrals,
closed forms, and Monte Carlo of the ray-tracer's counting rule (a ray that crosses a cell and ends
outside it is a miss, its misses stopped short of the sample (hit_stop); a sample inside is
a hit, or a miss for a max-range component)."""

import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from gmm_core import Grid
from gmm_core.analytic.cells import component_evidence, scan_evidence
from gmm_core.analytic.evidence_2d import analytic_map_2d
from gmm_core.reconstruct import reconstruct
from support.evidence import hit_stop, monte_carlo, two_scans_2d
from support.paper import eq5_by_angles, eq5_geometry


def rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def isotropic(cov):
    lam, vec = np.linalg.eigh(cov)
    return (vec / np.sqrt(lam)).T


def rect_mass_reference(mean, cov, lo, hi):
    """Eq. 10 over the rectangle [lo, hi]: integral over x of the conditional probability of y in it."""
    if not np.all(np.asarray(hi) > np.asarray(lo)):
        return 0.0
    sx, sy = np.sqrt(np.diag(cov))
    r = cov[0, 1] / (sx * sy)
    s = sy * math.sqrt(1 - r * r)

    def integrand(x):
        my = mean[1] + r * sy * (x - mean[0]) / sx
        return stats.norm.pdf(x, mean[0], sx) * (stats.norm.cdf((hi[1] - my) / s) - stats.norm.cdf((lo[1] - my) / s))

    return integrate.quad(integrand, lo[0], hi[0], epsabs=1e-14, epsrel=1e-12, limit=400)[0]


def square_mass_reference(mean, cov, center, size):
    return rect_mass_reference(mean, cov, np.asarray(center) - size / 2, np.asarray(center) + size / 2)


def beyond_reference(mean, cov, origin, center, size):
    """Mass beyond the cell on rays from origin (Eq. 3): polar coordinates about the sensor in the
    isotropic frame; the radial integral from the exit distance is Eq. 4's bracket (closed form),
    the angular one is scipy.quad split at the corners' angles."""
    iso = isotropic(cov)
    corners = np.asarray(center) + size / 2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    poly = (corners - mean) @ iso.T
    q = iso @ (np.asarray(origin) - mean)
    a, b = poly[1] - poly[0], poly[2] - poly[1]
    if a[0] * b[1] - a[1] * b[0] < 0:
        poly = poly[::-1]
    inward = np.array([[-(poly[(i + 1) % 4] - poly[i])[1], (poly[(i + 1) % 4] - poly[i])[0]] for i in range(4)])
    base = math.atan2(*(poly.mean(axis=0) - q)[::-1])
    angles = (np.array([math.atan2(*(v - q)[::-1]) for v in poly]) - base + np.pi) % (2 * np.pi) - np.pi

    def integrand(t):
        u = np.array([math.cos(t + base), math.sin(t + base)])
        r_exit = min(-(inward[i] @ (q - poly[i])) / (inward[i] @ u) for i in range(4) if inward[i] @ u < 0)
        a = -(q @ u)
        return (
            math.exp(-(q @ q - a * a) / 2)
            / (2 * math.pi)
            * (math.exp(-((r_exit - a) ** 2) / 2) + a * math.sqrt(math.pi / 2) * math.erfc((r_exit - a) / math.sqrt(2)))
        )

    inner = sorted(angles)[1:-1]
    return integrate.quad(integrand, angles.min(), angles.max(), points=inner, epsabs=1e-13, epsrel=1e-12, limit=400)[0]


def random_case_2d(rng, kind, thinnest=None):
    """A component, a sensor and a cell: kind 0 cell inside the component, 1 on the beam in front of
    or behind it, 2 beside it, 3 holding or touching the sensor."""
    sd = 10 ** rng.uniform(-2.3, -0.5, 2)
    if thinnest is not None:
        sd[0] = thinnest
    rot = rotation(rng.uniform(0, np.pi))
    cov = rot @ np.diag(sd**2) @ rot.T
    mean = rng.uniform(-3, 3, 2)
    origin = mean + rng.normal(0, 1, 2) * rng.uniform(0.2, 4)
    size = 10 ** rng.uniform(-2, -0.5)
    center = [
        mean + rot @ (rng.normal(0, 1, 2) * sd),
        origin + (mean - origin) * rng.uniform(0.05, 1.5),
        mean + rot @ (rng.normal(0, 4, 2) * sd),
        origin + rng.uniform(-0.7, 0.7, 2) * size,
    ][kind]
    return mean, cov, origin, center, size


def test_eq5_matches_its_scipy_twin_and_the_wedge_integral_in_front_of_the_component():
    rng = np.random.default_rng(4)
    p, r = rng.uniform(0, 50, 200), rng.uniform(0, 60, 200)
    t1, t2 = np.sort(rng.uniform(-1.5, 1.5, (2, 200)), axis=0)
    twin = (
        0.25
        * special.erfc((r - p) / np.sqrt(2))
        * (special.erf(p * np.sin(t2) / np.sqrt(2)) - special.erf(p * np.sin(t1) / np.sqrt(2)))
    )
    np.testing.assert_allclose(eq5_by_angles(p, t1, t2, r), twin, rtol=1e-12, atol=1e-15)
    for _ in range(20):
        # A cell at least 7 isotropic units in front of the mean, sensor far outside: Eq. 5 with the
        # cell's far radial distance is then exact up to the dropped mass (< 1e-10).
        mean, cov, origin, _, size = random_case_2d(rng, 1)
        center = origin + (mean - origin) * rng.uniform(0.05, 0.6)
        p_, theta1, theta2, r_near = eq5_geometry(mean, cov, origin, center[None], size)
        if p_[0] * (1 - 0.6) < 12 or r_near[0] > p_[0] - 12:
            continue
        reference = beyond_reference(mean, cov, origin, center, size)
        assert eq5_by_angles(p_, theta1, theta2, r_near)[0] == pytest.approx(reference, abs=1e-9)
        misses = component_evidence(mean, cov, origin, center[None], size)[1][0]
        assert misses == pytest.approx(reference, abs=1e-9)


@pytest.mark.parametrize("kind", [0, 1, 2, 3], ids=["inside", "on-beam", "beside", "at-sensor"])
def test_2d_hits_and_misses_match_numerical_integration(kind):
    rng = np.random.default_rng(10 + kind)
    for _ in range(25):
        mean, cov, origin, center, size = random_case_2d(rng, kind)
        hits, misses = component_evidence(mean, cov, origin, center[None], size)
        hits_free, misses_free = component_evidence(mean, cov, origin, center[None], size, max_range=True)
        mass = square_mass_reference(mean, cov, center, size)
        holds_sensor = np.all(np.abs(origin - center) <= size / 2)
        beyond = 1 - mass if holds_sensor else beyond_reference(mean, cov, origin, center, size)
        if holds_sensor:
            stopped = beyond
        else:
            # The occupied samples' misses, stopped short (evidence_2d.cell_evidence_2d): the square
            # scaled about the sensor so that its distance grows by the stop, and beyond it, less its
            # overlap with the cell.
            grow = 1 + hit_stop(cov, size) / np.linalg.norm(center - origin)
            far, far_size = origin + grow * (center - origin), grow * size
            lo = np.maximum(center - size / 2, far - far_size / 2)
            overlap = rect_mass_reference(mean, cov, lo, np.minimum(center + size / 2, far + far_size / 2))
            stopped = (
                square_mass_reference(mean, cov, far, far_size)
                + beyond_reference(mean, cov, origin, far, far_size)
                - overlap
            )
        # Both sides are exact; the tolerance is quad's accuracy on these integrands.
        assert hits[0] == pytest.approx(mass, abs=1e-8)
        assert misses[0] == pytest.approx(stopped, abs=1e-7)
        assert hits_free[0] == 0.0
        assert misses_free[0] == pytest.approx(beyond + mass, abs=1e-7)


@pytest.mark.parametrize("thinnest", [1e-4, 1e-7], ids=["thin", "nearly-degenerate"])
def test_2d_evidence_matches_monte_carlo_for_thin_components(thinnest):
    rng = np.random.default_rng(20)
    n = 200_000
    for kind in (0, 0, 1, 1, 2, 3):
        mean, cov, origin, center, size = random_case_2d(rng, kind, thinnest=thinnest)
        hits, misses = component_evidence(mean, cov, origin, center[None], size)
        # The cell that holds the sensor: every sample outside it is a miss, where the tracer leaves out
        # those within the stop of the sensor (evidence_2d.cell_evidence_2d), as in 3D.
        stop = 0.0 if kind == 3 else hit_stop(cov, size)
        mc_hits, mc_misses = monte_carlo(mean, cov, origin, center, size, n, rng, stop=stop)
        assert np.isfinite([hits[0], misses[0]]).all()
        # 5 binomial standard deviations of the Monte-Carlo fractions (plus 1e-4 for tiny ones).
        for value, mc in ((hits[0], mc_hits), (misses[0], mc_misses)):
            assert value == pytest.approx(mc, abs=5 * math.sqrt(mc * (1 - mc) / n) + 1e-4)


def test_cell_holding_the_sensor_is_crossed_by_every_ray():
    cov = np.array([[0.04, 0.01], [0.01, 0.01]])
    mean = np.array([2.0, 0.5])
    # The sensor at the cell's centre, on its lower corner, and at the component's mean in the cell.
    for origin, cell in (([0.0, 0.0], [0.0, 0.0]), ([-0.05, -0.05], [0.0, 0.0]), (mean, mean + 0.02)):
        hits, misses = component_evidence(mean, cov, origin, np.array([cell]), 0.1)
        assert 0 <= hits[0] < 1 and misses[0] == pytest.approx(1 - hits[0], abs=1e-12)
        assert component_evidence(mean, cov, origin, np.array([cell]), 0.1, max_range=True)[1][0] == 1.0
    # The sensor on the corner shared by four cells (round grid coordinates): as in the ray tracer,
    # the upper one holds it and the others see the rays heading into them.
    corner_cells = np.array([[0.05, 0.05], [-0.05, 0.05], [-0.05, -0.05], [0.05, -0.05]])
    corner_cells += 1.0  # cell centres with round-off, as a grid computes them
    sensor = np.array([1.0, 1.0])
    hits, misses = component_evidence(mean + 1.0, cov, sensor, corner_cells, 0.1)
    assert misses[0] == pytest.approx(1 - hits[0], abs=1e-12)
    rng = np.random.default_rng(5)
    for c, h, m in zip(corner_cells[1:], hits[1:], misses[1:]):
        mc_h, mc_m = monte_carlo(mean + 1.0, cov, sensor, c, 0.1, 200_000, rng, stop=hit_stop(cov, 0.1))
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=5e-3)
    # A sensor at the mean, cells around it: finite, in [0, 1], and rays reach the cells beyond.
    centers = np.array([[2.3, 0.5], [2.0, 0.9], [1.7, 0.2], [2.0, 0.5]])
    hits, misses = component_evidence(mean, cov, mean, centers, 0.1)
    assert np.isfinite(hits).all() and np.isfinite(misses).all()
    assert np.all((hits >= 0) & (misses >= 0) & (hits + misses <= 1 + 1e-12))
    for c, h, m in zip(centers, hits, misses):
        stop = 0.0 if np.all(np.abs(mean - c) <= 0.05) else hit_stop(cov, 0.1)
        mc_h, mc_m = monte_carlo(mean, cov, mean, c, 0.1, 200_000, rng, stop=stop)
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=5e-3)


def test_analytic_map_equals_the_per_cell_evaluation_and_matches_monte_carlo():
    models = two_scans_2d()
    grid = Grid(np.array([-0.5, -1.5]), 0.1, (35, 50))
    hits, misses = analytic_map_2d(models, grid)
    cell_hits, cell_misses = scan_evidence(models, grid.cell_centers(), grid.resolution)
    # The same pairs, rasterised per component or looped per cell: equal up to summation order.
    np.testing.assert_allclose(hits.ravel(), cell_hits, atol=1e-9)
    np.testing.assert_allclose(misses.ravel(), cell_misses, atol=1e-9)
    # Culling at 5 sigma drops less than 1e-5 of each component (Q(5) = 3e-7 per side).
    exact_hits, exact_misses = np.zeros(grid.n_cells), np.zeros(grid.n_cells)
    for model, pose in models:
        for mixture, free in ((model.occupied, False), (model.free, True)):
            world = mixture.transformed(pose)
            for w, mu, cov in zip(world.weights, world.means, world.covariances):
                h, m = component_evidence(mu, cov, pose.t, grid.cell_centers(), grid.resolution, max_range=free)
                exact_hits += world.support * w * h
                exact_misses += world.support * w * m
    np.testing.assert_allclose(cell_hits, exact_hits, atol=1e-4)
    np.testing.assert_allclose(cell_misses, exact_misses, atol=1e-4)
    # Monte-Carlo reconstruction of the same models (both sensors on grid corners): totals agree,
    # and cell by cell within the noise of its 4096 samples per component (a count of 20 varies by
    # up to 20 * 0.5 / 64 = 0.16 per component; cells on one beam share rays).
    mc_hits, mc_misses = reconstruct(grid, [(m, p, 7) for m, p in models], samples_per_cell=400.0)
    assert hits.sum() == pytest.approx(mc_hits.sum(), rel=1e-3)
    assert misses.sum() == pytest.approx(mc_misses.sum(), rel=5e-3)
    assert np.abs(hits - mc_hits).max() < 0.3 and np.abs(misses - mc_misses).max() < 1.0


def test_intel_analytic_map_is_as_good_as_monte_carlo(intel_scans):
    """Issue 3's bar: at 10 cm, AUROC against the counting grid >= 0.98 and within 0.01 of MC."""
    from gmm_core import FitConfig, fit_scan
    from gmm_core.metrics import grid_auroc
    from gmm_core.occupancy import map_estimate
    from gmm_core.reconstruct import count_beams
    from gmm_core.sampling import scan_seed
    from services.replay import data_extent

    config = FitConfig()
    models = [fit_scan(s.hits, s.no_return, config) for s in intel_scans]
    grid = Grid.from_bbox(*data_extent(intel_scans, config.max_range), 0.1)
    truth = count_beams(grid, [(s.hits, s.no_return, s.pose) for s in intel_scans], config.max_range)
    analytic_p = map_estimate(*analytic_map_2d([(m, s.pose) for m, s in zip(models, intel_scans)], grid))
    mc_p = map_estimate(
        *reconstruct(
            grid, [(m, s.pose, scan_seed(0, s.index)) for m, s in zip(models, intel_scans)], samples_per_cell=4.0
        )
    )
    analytic_auroc, mc_auroc = grid_auroc(analytic_p, *truth), grid_auroc(mc_p, *truth)
    assert analytic_auroc >= 0.98 and abs(analytic_auroc - mc_auroc) <= 0.01
