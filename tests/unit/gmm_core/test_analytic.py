"""gmm_core.analytic against references: scipy quadrature of the defining integrals, closed forms,
and Monte Carlo of the ray-tracer's counting rule (a ray that crosses a cell and ends outside it
is a miss; a sample inside is a hit, or a miss for a max-range component)."""
import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from gmm_core import Grid, Mixture, Pose, ScanModel
from gmm_core import analytic
from gmm_core.analytic import (analytic_map_2d, component_evidence, eq5, eq5_geometry, occupancy_at_cells,
                               polygon_mass, scan_evidence)
from gmm_core.reconstruct import reconstruct


# --- references -------------------------------------------------------------------------------

def rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def random_rotation_3d(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def isotropic(cov):
    lam, vec = np.linalg.eigh(cov)
    return (vec / np.sqrt(lam)).T


def monte_carlo(mean, cov, origin, center, size, n, rng, max_range=False):
    """(hit, miss) fractions of one cell, from n rays origin -> sample (slab test per ray)."""
    x = rng.multivariate_normal(mean, cov, n)
    lo, hi = np.asarray(center) - size / 2, np.asarray(center) + size / 2
    o = np.asarray(origin, dtype=float)
    d = x - o
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    inside_o = (o >= lo) & (o <= hi)
    t_enter = np.where(d != 0, np.minimum(ta, tb), np.where(inside_o, -np.inf, np.inf)).max(axis=1)
    t_exit = np.where(d != 0, np.maximum(ta, tb), np.where(inside_o, np.inf, -np.inf)).min(axis=1)
    crosses = (t_enter < t_exit) & (t_exit > 0) & (t_enter < 1)  # a length of the ray inside
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    if max_range:
        return 0.0, crosses.mean()
    return inside.mean(), (crosses & ~inside).mean()


def rect_mass_reference(mean, cov, center, size):
    """Eq. 10 over a square: integral over x of the conditional probability of y in the cell."""
    h = size / 2
    sx, sy = np.sqrt(np.diag(cov))
    r = cov[0, 1] / (sx * sy)
    s = sy * math.sqrt(1 - r * r)

    def integrand(x):
        my = mean[1] + r * sy * (x - mean[0]) / sx
        return stats.norm.pdf(x, mean[0], sx) * (stats.norm.cdf((center[1] + h - my) / s)
                                                  - stats.norm.cdf((center[1] - h - my) / s))

    return integrate.quad(integrand, center[0] - h, center[0] + h, epsabs=1e-14, epsrel=1e-12, limit=400)[0]


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
        return math.exp(-(q @ q - a * a) / 2) / (2 * math.pi) * (
            math.exp(-(r_exit - a) ** 2 / 2) + a * math.sqrt(math.pi / 2) * math.erfc((r_exit - a) / math.sqrt(2)))

    inner = sorted(angles)[1:-1]
    return integrate.quad(integrand, angles.min(), angles.max(), points=inner,
                          epsabs=1e-13, epsrel=1e-12, limit=400)[0]


def polygon_mass_reference(vertices):
    """Standard normal mass of a convex polygon: integral over x of Phi(y_top) - Phi(y_bottom)."""
    v = np.asarray(vertices)
    edges = [(v[i], v[(i + 1) % len(v)]) for i in range(len(v))]

    def y_span(x):
        ys = [a[1] + (b[1] - a[1]) * (x - a[0]) / (b[0] - a[0]) for a, b in edges
              if a[0] != b[0] and min(a[0], b[0]) <= x <= max(a[0], b[0])]
        return (min(ys), max(ys)) if ys else (0.0, 0.0)

    def integrand(x):
        low, high = y_span(x)
        return stats.norm.pdf(x) * (stats.norm.cdf(high) - stats.norm.cdf(low))

    return integrate.quad(integrand, v[:, 0].min(), v[:, 0].max(), points=sorted(v[:, 0]),
                          epsabs=1e-13, epsrel=1e-12, limit=400)[0]


def random_convex_polygon(rng):
    n = rng.integers(3, 8)
    angles = np.sort(rng.uniform(0, 2 * np.pi, n))
    radius = 10 ** rng.uniform(-1, 0.7) * rng.uniform(0.2, 1, 2)
    return rng.normal(0, 1.5, 2) + radius * np.column_stack([np.cos(angles), np.sin(angles)])


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
    center = [mean + rot @ (rng.normal(0, 1, 2) * sd),
              origin + (mean - origin) * rng.uniform(0.05, 1.5),
              mean + rot @ (rng.normal(0, 4, 2) * sd),
              origin + rng.uniform(-0.7, 0.7, 2) * size][kind]
    return mean, cov, origin, center, size


# --- special functions and polygons ----------------------------------------------------------

def test_bivariate_normal_orthant_matches_quadrature():
    rng = np.random.default_rng(1)
    for _ in range(80):
        h, k = rng.normal(0, 2, 2)
        r = rng.uniform(-0.999, 0.999)
        reference = integrate.quad(
            lambda x: stats.norm.pdf(x) * stats.norm.sf((k - r * x) / math.sqrt(1 - r * r)),
            h, np.inf, epsabs=1e-14, epsrel=1e-12)[0]
        # Genz's algorithm is good to ~1e-15; quad to ~1e-12 here.
        assert analytic._bvn_upper(h, k, r) == pytest.approx(reference, abs=1e-10)
    # Fully correlated limits: one half-line, or the interval between the two bounds.
    assert analytic._bvn_upper(0.3, -0.2, 1.0) == pytest.approx(stats.norm.sf(0.3), abs=1e-15)
    between = stats.norm.cdf(0.2) - stats.norm.cdf(-0.3)
    assert analytic._bvn_upper(-0.3, -0.2, -1.0) == pytest.approx(between, abs=1e-15)


def test_polygon_mass_exact_and_by_green_with_the_erf_approximation():
    rng = np.random.default_rng(2)
    for _ in range(40):
        vertices = random_convex_polygon(rng)
        reference = polygon_mass_reference(vertices)
        assert polygon_mass(vertices) == pytest.approx(reference, abs=1e-10)
        assert polygon_mass(vertices[::-1]) == pytest.approx(reference, abs=1e-10)  # either orientation
        # Eq. 9: erf replaced by Eq. 7 (max error 0.014) along the path, weighted by
        # e^{-x^2/2}/sqrt(8 pi); measured at most 0.012 on polygons covering most of the mass.
        assert polygon_mass(vertices, approximate=True) == pytest.approx(reference, abs=0.013)


def test_edge_integral_eq8_is_the_closed_form_of_the_approximated_integrand():
    rng = np.random.default_rng(3)

    def erf_hat(x):  # Eq. 7
        return np.sign(x) * (1 - np.exp(-2 / np.pi * np.abs(x) * (np.abs(x) + np.sqrt(np.pi))))

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
        integrand = lambda x: math.exp(-x * x / 2) * erf_hat((y0 + slope * (x - x0)) / math.sqrt(2))  # noqa: E731
        reference = integrate.quad(integrand, x0, x1, points=bends, epsabs=1e-13, epsrel=1e-12, limit=400)[0]
        got = analytic._edge_piece_eq8(x0, y0, x1, y1, sign)
        assert got == pytest.approx(reference, abs=1e-11)


# --- 2D ---------------------------------------------------------------------------------------

def test_eq5_matches_its_scipy_twin_and_the_wedge_integral_in_front_of_the_component():
    rng = np.random.default_rng(4)
    p, r = rng.uniform(0, 50, 200), rng.uniform(0, 60, 200)
    t1, t2 = np.sort(rng.uniform(-1.5, 1.5, (2, 200)), axis=0)
    twin = 0.25 * special.erfc((r - p) / np.sqrt(2)) * (special.erf(p * np.sin(t2) / np.sqrt(2))
                                                         - special.erf(p * np.sin(t1) / np.sqrt(2)))
    np.testing.assert_allclose(eq5(p, t1, t2, r), twin, rtol=1e-12, atol=1e-15)
    for _ in range(20):
        # A cell at least 7 isotropic units in front of the mean, sensor far outside: Eq. 5 with the
        # cell's far radial distance is then exact up to the dropped mass (< 1e-10).
        mean, cov, origin, _, size = random_case_2d(rng, 1)
        center = origin + (mean - origin) * rng.uniform(0.05, 0.6)
        p_, theta1, theta2, r_near = eq5_geometry(mean, cov, origin, center[None], size)
        if p_[0] * (1 - 0.6) < 12 or r_near[0] > p_[0] - 12:
            continue
        reference = beyond_reference(mean, cov, origin, center, size)
        assert eq5(p_, theta1, theta2, r_near)[0] == pytest.approx(reference, abs=1e-9)
        misses = component_evidence(mean, cov, origin, center[None], size)[1][0]
        assert misses == pytest.approx(reference, abs=1e-9)


@pytest.mark.parametrize("kind", [0, 1, 2, 3], ids=["inside", "on-beam", "beside", "at-sensor"])
def test_2d_hits_and_misses_match_numerical_integration(kind):
    rng = np.random.default_rng(10 + kind)
    for _ in range(25):
        mean, cov, origin, center, size = random_case_2d(rng, kind)
        hits, misses = component_evidence(mean, cov, origin, center[None], size)
        hits_free, misses_free = component_evidence(mean, cov, origin, center[None], size, max_range=True)
        mass = rect_mass_reference(mean, cov, center, size)
        holds_sensor = np.all(np.abs(origin - center) <= size / 2)
        beyond = 1 - mass if holds_sensor else beyond_reference(mean, cov, origin, center, size)
        # Both sides are exact; the tolerance is quad's accuracy on these integrands.
        assert hits[0] == pytest.approx(mass, abs=1e-8)
        assert misses[0] == pytest.approx(beyond, abs=1e-7)
        assert hits_free[0] == 0.0
        assert misses_free[0] == pytest.approx(beyond + mass, abs=1e-7)


@pytest.mark.parametrize("thinnest", [1e-4, 1e-7], ids=["thin", "nearly-degenerate"])
def test_2d_evidence_matches_monte_carlo_for_thin_components(thinnest):
    rng = np.random.default_rng(20)
    n = 200_000
    for kind in (0, 0, 1, 1, 2, 3):
        mean, cov, origin, center, size = random_case_2d(rng, kind, thinnest=thinnest)
        hits, misses = component_evidence(mean, cov, origin, center[None], size)
        mc_hits, mc_misses = monte_carlo(mean, cov, origin, center, size, n, rng)
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
        mc_h, mc_m = monte_carlo(mean + 1.0, cov, sensor, c, 0.1, 200_000, rng)
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=5e-3)
    # A sensor at the mean, cells around it: finite, in [0, 1], and rays reach the cells beyond.
    centers = np.array([[2.3, 0.5], [2.0, 0.9], [1.7, 0.2], [2.0, 0.5]])
    hits, misses = component_evidence(mean, cov, mean, centers, 0.1)
    assert np.isfinite(hits).all() and np.isfinite(misses).all()
    assert np.all((hits >= 0) & (misses >= 0) & (hits + misses <= 1 + 1e-12))
    for c, h, m in zip(centers, hits, misses):
        mc_h, mc_m = monte_carlo(mean, cov, mean, c, 0.1, 200_000, rng)
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=5e-3)


# --- 3D ---------------------------------------------------------------------------------------

def random_case_3d(rng, kind):
    rot = random_rotation_3d(rng)
    sd = np.sort(10 ** rng.uniform(-2, -0.6, 3))
    if kind == 4:
        sd[0] = 1e-6  # a nearly degenerate (flat) component
    cov = rot @ np.diag(sd**2) @ rot.T
    mean = rng.uniform(-2, 2, 3)
    origin = mean + rng.normal(0, 1, 3) * rng.uniform(0.5, 3)
    size = 10 ** rng.uniform(-1.3, -0.6)
    center = [mean + rot @ (rng.normal(0, 1, 3) * sd),
              origin + (mean - origin) * rng.uniform(0.3, 1.2) + rng.normal(0, 0.5, 3) * sd[-1],
              mean + rot @ (rng.normal(0, 3, 3) * sd),
              origin + rng.uniform(-0.5, 0.5, 3) * size,
              mean + rot @ (rng.normal(0, 1, 3) * sd)][kind]
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
        mc_hits, mc_misses = monte_carlo(mean, cov, origin, center, size, n, rng)
        _, mc_free = monte_carlo(mean, cov, origin, center, size, n, rng, max_range=True)
        assert np.isfinite([hits[0], misses[0], misses_free[0]]).all()
        # Near the component both are exact up to quadrature; well in front of it misses use the
        # erf approximation of Eq. 9, good to 0.012 of the component's mass (see the polygon test).
        pairs = ((hits[0], mc_hits, 0.0), (misses[0], mc_misses, 0.012), (misses_free[0], mc_free, 0.012))
        for value, mc, slack in pairs:
            assert value == pytest.approx(mc, abs=5 * math.sqrt(mc * (1 - mc) / n) + 1e-4 + slack)


def test_3d_sensor_on_a_corner_shared_by_eight_cubes():
    rng = np.random.default_rng(8)
    mean, cov = np.array([1.3, 1.1, 0.9]), np.diag([0.05, 0.2, 0.1]) ** 2
    sensor = np.array([1.0, 1.0, 1.0])
    offsets = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)]) - 0.5
    centers = sensor + 0.1 * offsets  # with round-off, as a grid computes them
    hits, misses = component_evidence(mean, cov, sensor, centers, 0.1)
    assert misses[7] == pytest.approx(1 - hits[7], abs=1e-12)  # the upper cube holds the sensor
    for c, h, m in zip(centers[:7], hits[:7], misses[:7]):
        mc_h, mc_m = monte_carlo(mean, cov, sensor, c, 0.1, 200_000, rng)
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
        mc_h, mc_m = monte_carlo(mean, cov, origin, c, 0.1, n, rng)
        assert (h, m) == pytest.approx((mc_h, mc_m), abs=2e-3)  # > 4 standard deviations at 1e6


# --- many components, maps --------------------------------------------------------------------

def two_scans_2d():
    """Two small scans of a corner, seen from two poses; every mixture has a free part too."""
    wall = Mixture(np.array([0.5, 0.5]), np.array([[2.0, -0.3], [2.0, 0.4]]),
                   np.array([np.diag([1e-4, 0.04]), np.diag([2e-4, 0.02])]), 40)
    free = Mixture(np.ones(1), np.array([[0.5, 2.5]]), np.diag([0.05, 1e-4])[None], 10)
    scan = ScanModel(wall, free, np.zeros(2), 3.0)
    return [(scan, Pose.from_xytheta(0.0, 0.0, 0.0)), (scan, Pose.from_xytheta(0.3, -0.5, 0.2))]


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


def test_occupancy_at_cells_is_eq11_of_the_evidence_and_the_prior_where_unseen():
    models = two_scans_2d()[:1]
    cells = np.array([[2.0, -0.3], [2.0, 0.4], [1.0, 0.0], [2.5, 0.0], [-5.0, 5.0]])
    hits, misses = scan_evidence(models, cells, 0.05)
    p = occupancy_at_cells(models, cells, 0.05, prior=0.2)
    np.testing.assert_allclose(p, (hits + 0.2) / (hits + misses + 0.4), rtol=1e-6)
    assert p[0] > 0.8 and p[1] > 0.8  # on the wall
    assert p[2] < 0.15  # in the free space in front of it (about 1.5 misses against N_p = 0.2)
    assert p[3] == p[4] == 0.5  # behind the wall, and far away: never observed
    assert occupancy_at_cells([], cells, 0.05).tolist() == [0.5] * 5


def test_3d_scan_evidence_and_dimension_checks():
    flat = Mixture(np.ones(1), np.array([[2.0, 0.0, 0.0]]), np.diag([1e-4, 0.04, 0.04])[None], 50)
    scan = ScanModel(flat, Mixture.empty(3), np.zeros(3), 10.0)
    cells = np.array([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    hits, misses = scan_evidence([(scan, Pose.identity(3))], cells, 0.1)
    # 50 points over a 20 cm x 20 cm patch: about 2 in the 10 cm cube at its centre.
    assert hits[0] > 1.5 and hits[1] == 0 and misses[1] > 1.5 and hits[2] == misses[2] == 0
    with pytest.raises(ValueError, match="2D"):
        analytic_map_2d([(scan, Pose.identity(3))], Grid(np.zeros(3), 0.1, (2, 2, 2)))
    with pytest.raises(ValueError, match="2D points"):
        scan_evidence([(scan, Pose.identity(3))], np.zeros((1, 2)), 0.1)
    with pytest.raises(ValueError, match="cell_size"):
        scan_evidence([(scan, Pose.identity(3))], cells, 0.0)


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
    mc_p = map_estimate(*reconstruct(grid, [(m, s.pose, scan_seed(0, s.index)) for m, s in zip(models, intel_scans)],
                                     samples_per_cell=4.0))
    analytic_auroc, mc_auroc = grid_auroc(analytic_p, *truth), grid_auroc(mc_p, *truth)
    assert analytic_auroc >= 0.98 and abs(analytic_auroc - mc_auroc) <= 0.01
