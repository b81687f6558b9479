"""Analytic hit and miss evidence of Gaussian mixtures over cells, without sampling (Sec. III-C, III-D).

The Monte-Carlo path (gmm_core.reconstruct) samples every component, casts a ray from the sensor
origin to each sample and counts, per cell, the rays that cross the cell (misses) and the samples
inside it (hits). This module computes the expected counts for any cell directly:

- hits (Eq. 10): N pi_k times the component's mass inside the cell. A square exactly, as a
  bivariate normal rectangle probability; a cube by quadrature over slices across the
  component's thinnest axis, each slice an exact polygon probability.
- misses (Eq. 3): N pi_k times the component's mass lying beyond the cell on rays from the
  sensor. In the isotropic frame x_I = S^-1/2 V^T (x - mu) the component is N(0, I) and rays
  stay rays (the map is affine), so the question is the standard normal mass of a region.
  2D: Eq. 5 where it is exact to 1e-10 (the cell lies well in front of the component and the
  sensor well outside it); elsewhere exactly, as the mass of the cell's wedge minus that of the
  convex hull of sensor and cell, by Brianchon-Gram (one bivariate normal orthant per corner).
  3D: well in front of the component the paper's Eq. 6-9 (the cube's shadow cast from the
  sensor onto the plane through the mean across the beam, integrated by Green's theorem with
  the erf approximation of Eq. 7; error up to 0.012 of the component's mass); near it exactly,
  as the mass of C(V) = the cone from the sensor over the cube beyond the cube's entry (a convex
  polyhedron) minus the cube's own, by the same slices as the hits.

What counts follows gmm_core.raytrace: a sample whose ray crosses the cell and ends outside it
is a miss of the cell; a sample inside the cell is a hit when it comes from the occupied mixture
and a miss when it comes from the free (max-range) mixture. The cell holding the sensor (by the
tracer's floor convention: -h <= s - c < h per axis) is crossed by every ray.

Conventions: a cell is given by its centre and side (square in 2D, cube in 3D, axis-aligned);
masses are fractions of one component (multiply by N pi_k for counts).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate

SQRT2 = math.sqrt(2.0)
SQRT_2PI = math.sqrt(2.0 * math.pi)
SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)
NEGLIGIBLE_SIGMA = 7.0  # isotropic distance beyond which a component's mass (< 2.3e-11) is dropped
REACH_SIGMA = 5.0  # culling: a component reaches cells within the cone of its 5-sigma ellipse

# Gauss-Legendre abscissae (the negative half) and weights for Genz's bivariate normal: 6, 12, 20 points.
_GL6_X, _GL6_W = (a[:3].copy() for a in np.polynomial.legendre.leggauss(6))
_GL12_X, _GL12_W = (a[:6].copy() for a in np.polynomial.legendre.leggauss(12))
_GL20_X, _GL20_W = (a[:10].copy() for a in np.polynomial.legendre.leggauss(20))
# Gauss-Legendre rule on [-1, 1] for the slices of a cube (_cube_masses_3d).
_SLICE_X, _SLICE_W = np.polynomial.legendre.leggauss(6)


# ---------------------------------------------------------------------------------------------
# Special functions
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _norm_sf(x):
    """Q(x) = P(X > x), X ~ N(0, 1)."""
    return 0.5 * math.erfc(x / SQRT2)


@njit(cache=True)
def _erf_diff(a, b):
    """erf(b) - erf(a), without cancellation in the tails."""
    if a > 0.0 and b > 0.0:
        return math.erfc(a) - math.erfc(b)
    if a < 0.0 and b < 0.0:
        return math.erfc(-b) - math.erfc(-a)
    return math.erf(b) - math.erf(a)


@njit(cache=True)
def _norm_ppf_lower(t):
    """Phi^-1(t) for 0 < t <= 0.5: Acklam's rational approximation and one Halley step."""
    if t < 0.02425:
        q = math.sqrt(-2.0 * math.log(t))
        x = ((((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00)
             / ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
                 + 3.754408661907416e+00) * q + 1.0))
    else:
        q = t - 0.5
        r = q * q
        x = ((((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02) * r
                + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q
             / (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02) * r
                  + 6.680131188771972e+01) * r - 1.328068155288572e+01) * r + 1.0))
    e = 0.5 * math.erfc(-x / SQRT2) - t
    u = e * SQRT_2PI * math.exp(0.5 * x * x)
    return x - u / (1.0 + 0.5 * x * u)


@njit(cache=True)
def _bvn_upper(h, k, r):
    """P(X > h, Y > k) for standard normals with correlation r (Genz 2004, 'BVNU', ~1e-15)."""
    ar = abs(r)
    if ar < 0.3:
        xs, ws = _GL6_X, _GL6_W
    elif ar < 0.75:
        xs, ws = _GL12_X, _GL12_W
    else:
        xs, ws = _GL20_X, _GL20_W
    hk = h * k
    if ar < 0.925:
        hs = 0.5 * (h * h + k * k)
        asr = math.asin(r)
        total = 0.0
        for i in range(xs.shape[0]):
            for sign in (1.0, -1.0):
                sn = math.sin(0.5 * asr * (sign * xs[i] + 1.0))
                total += ws[i] * math.exp((sn * hk - hs) / (1.0 - sn * sn))
        return total * asr / (4.0 * math.pi) + _norm_sf(h) * _norm_sf(k)
    if r < 0.0:
        k = -k
        hk = -hk
    total = 0.0
    if ar < 1.0:
        a2 = (1.0 - r) * (1.0 + r)
        a = math.sqrt(a2)
        bs = (h - k) ** 2
        c = (4.0 - hk) / 8.0
        d = (12.0 - hk) / 16.0
        total = a * math.exp(-0.5 * (bs / a2 + hk)) * (
            1.0 - c * (bs - a2) * (1.0 - d * bs / 5.0) / 3.0 + c * d * a2 * a2 / 5.0)
        if hk > -160.0:
            b = math.sqrt(bs)
            total -= (math.exp(-0.5 * hk) * SQRT_2PI * _norm_sf(b / a) * b
                      * (1.0 - c * bs * (1.0 - d * bs / 5.0) / 3.0))
        a *= 0.5
        for i in range(xs.shape[0]):
            for sign in (1.0, -1.0):
                x2 = (a * (sign * xs[i] + 1.0)) ** 2
                rs = math.sqrt(1.0 - x2)
                asr = -0.5 * (bs / x2 + hk)
                if asr > -100.0:
                    total += a * ws[i] * math.exp(asr) * (
                        math.exp(-hk * x2 / (2.0 * (1.0 + rs) ** 2)) / rs - (1.0 + c * x2 * (1.0 + d * x2)))
        total = -total / (2.0 * math.pi)
    if r > 0.0:
        return total + _norm_sf(max(h, k))
    total = -total
    if k > h:
        if h < 0.0:
            total += _norm_sf(-k) - _norm_sf(-h)
        else:
            total += _norm_sf(h) - _norm_sf(k)
    return total


# ---------------------------------------------------------------------------------------------
# Standard bivariate normal mass of polygons
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _halfplane_mass(ax, ay, bx, by):
    """Mass left of the directed line a -> b (the inner side of an edge of a ccw polygon)."""
    ex, ey = bx - ax, by - ay
    length = math.hypot(ex, ey)
    if length == 0.0:
        return 0.0
    return _norm_sf((-ey * ax + ex * ay) / length)


@njit(cache=True)
def _corner_mass(vx, vy, nx_, ny_, px, py):
    """Mass of the wedge at corner v of a ccw polygon, between the rays to its next and previous
    corners: P(n1.X >= n1.v, n2.X >= n2.v), a bivariate normal orthant with rho = -cos(angle)."""
    d1x, d1y = nx_ - vx, ny_ - vy
    d2x, d2y = px - vx, py - vy
    l1 = math.hypot(d1x, d1y)
    l2 = math.hypot(d2x, d2y)
    if l1 == 0.0 or l2 == 0.0:
        return 0.0
    d1x, d1y, d2x, d2y = d1x / l1, d1y / l1, d2x / l2, d2y / l2
    rho = min(1.0, max(-1.0, -(d1x * d2x + d1y * d2y)))
    return _bvn_upper(-d1y * vx + d1x * vy, d2y * vx - d2x * vy, rho)


@njit(cache=True)
def _drop_repeated_corners(xs, ys, n):
    """Merge corners closer than 1e-9 of the polygon's size (clipping by coinciding planes leaves
    such pairs; the edge between them has a direction of pure round-off). Returns the new count."""
    size = max(xs[:n].max() - xs[:n].min(), ys[:n].max() - ys[:n].min())
    m = 0
    for i in range(n):
        if m == 0 or math.hypot(xs[i] - xs[m - 1], ys[i] - ys[m - 1]) > 1e-9 * size:
            xs[m], ys[m] = xs[i], ys[i]
            m += 1
    while m > 1 and math.hypot(xs[m - 1] - xs[0], ys[m - 1] - ys[0]) <= 1e-9 * size:
        m -= 1
    return m


@njit(cache=True)
def _polygon_mass_exact(xs, ys, n):
    """Standard normal mass of a convex ccw polygon (Brianchon-Gram: corners - edges + plane)."""
    if n >= 3:
        n = _drop_repeated_corners(xs, ys, n)
    if n < 3:
        return 0.0
    total = 1.0
    for i in range(n):
        j = (i + 1) % n
        h = (i + n - 1) % n
        total += _corner_mass(xs[i], ys[i], xs[j], ys[j], xs[h], ys[h])
        total -= _halfplane_mass(xs[i], ys[i], xs[j], ys[j])
    return min(max(total, 0.0), 1.0)


@njit(cache=True)
def _edge_piece_eq8(x0, y0, x1, y1, s):
    """int_{x0}^{x1} e^{-x^2/2} e_hat(y(x)/sqrt2) dx along a straight piece where sign(y) = s (Eq. 8).

    e_hat(y/sqrt2) = s (1 - exp(-y^2/pi - s y sqrt(2/pi))) (Eq. 7), so the integrand is
    e^{-x^2/2} minus a Gaussian in x; both integrate to erf. The quadratic exponent is expanded
    about x0 (not about x = 0 as in the paper's I_k), which stays exact for nearly vertical edges.
    """
    dx = x1 - x0
    m = (y1 - y0) / dx
    a = 0.5 + m * m / math.pi
    f0 = -0.5 * x0 * x0 - y0 * y0 / math.pi - s * y0 * SQRT_2_OVER_PI  # exponent at x0
    g0 = -x0 - m * (2.0 * y0 + s * SQRT_2PI) / math.pi  # its slope at x0
    ra = math.sqrt(a)
    shift = 0.5 * g0 / a
    peak = 0.5 * math.sqrt(math.pi / a) * math.exp(f0 + 0.25 * g0 * g0 / a)
    gauss = peak * _erf_diff(-ra * shift, ra * (dx - shift))
    return s * (SQRT_HALF_PI * _erf_diff(x0 / SQRT2, x1 / SQRT2) - gauss)


@njit(cache=True)
def _polygon_mass_eq9(xs, ys, n):
    """Standard normal mass of a ccw polygon by Green's theorem with the erf approximation (Eq. 6-9).

    mass = -1/sqrt(8 pi) * loop-integral e^{-x^2/2} erf(y/sqrt2) dx (Eq. 6; the minus sign is that
    of a counter-clockwise path), each edge split where it crosses y = 0 (Eq. 9).
    """
    total = 0.0
    for i in range(n):
        j = (i + 1) % n
        x0, y0, x1, y1 = xs[i], ys[i], xs[j], ys[j]
        if x0 == x1:
            continue
        if (y0 < 0.0 < y1) or (y1 < 0.0 < y0):
            xz = x0 + (x1 - x0) * y0 / (y0 - y1)
            total += _edge_piece_eq8(x0, y0, xz, 0.0, 1.0 if y0 > 0.0 else -1.0)
            total += _edge_piece_eq8(xz, 0.0, x1, y1, 1.0 if y1 > 0.0 else -1.0)
        else:
            total += _edge_piece_eq8(x0, y0, x1, y1, 1.0 if y0 + y1 >= 0.0 else -1.0)
    return min(max(-total / math.sqrt(8.0 * math.pi), 0.0), 1.0)


@njit(cache=True)
def _make_ccw(xs, ys, n):
    """Reverse a convex polygon's corners in place if they run clockwise."""
    area2 = 0.0
    for i in range(n):
        j = (i + 1) % n
        area2 += xs[i] * ys[j] - xs[j] * ys[i]
    if area2 < 0.0:
        for i in range(n // 2):
            xs[i], xs[n - 1 - i] = xs[n - 1 - i], xs[i]
            ys[i], ys[n - 1 - i] = ys[n - 1 - i], ys[i]


# ---------------------------------------------------------------------------------------------
# 2D: one component, one square cell
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _holds_sensor(sensor, center, half):
    """Whether the cell holds the sensor: -half <= s - c < half on every axis, the ray tracer's
    floor convention (a sensor on a shared boundary belongs to the upper cell), with round-off
    to spare so that neighbouring cells agree."""
    for i in range(sensor.shape[0]):
        offset = sensor[i] - center[i]
        if offset < -half * (1.0 + 1e-9) or offset >= half * (1.0 - 1e-9):
            return False
    return True


@njit(cache=True)
def _eq5(p, sin1, sin2, r_prime):
    """Eq. 5: 1/4 erfc((r' - p)/sqrt2) (erf(p sin(theta2)/sqrt2) - erf(p sin(theta1)/sqrt2)).

    Mass of N((p, 0), I) seen from the origin in the wedge theta1..theta2 beyond radius r'.
    """
    return 0.25 * math.erfc((r_prime - p) / SQRT2) * _erf_diff(p * sin1 / SQRT2, p * sin2 / SQRT2)


@njit(cache=True)
def _rect_mass_2d(mean, cov, cx, cy, half):
    """Eq. 10 over a square: the bivariate normal rectangle probability (4 orthants)."""
    sx = math.sqrt(cov[0, 0])
    sy = math.sqrt(cov[1, 1])
    r = min(1.0, max(-1.0, cov[0, 1] / (sx * sy)))
    x0, x1 = (cx - half - mean[0]) / sx, (cx + half - mean[0]) / sx
    y0, y1 = (cy - half - mean[1]) / sy, (cy + half - mean[1]) / sy
    # Reflect so the cell lies on the upper side of each axis: tail masses keep their digits.
    if x0 + x1 < 0.0:
        x0, x1, r = -x1, -x0, -r
    if y0 + y1 < 0.0:
        y0, y1, r = -y1, -y0, -r
    mass = _bvn_upper(x0, y0, r) - _bvn_upper(x1, y0, r) - _bvn_upper(x0, y1, r) + _bvn_upper(x1, y1, r)
    return min(max(mass, 0.0), 1.0)


@njit(cache=True)
def _beyond_exact_2d(qx, qy, px, py, radius):
    """Eq. 3 exactly: mass of the cell's wedge from the sensor q beyond the cell (ccw polygon px, py).

    wedge - hull(q, cell) = sum(edge half-planes) - sum(corner wedges) - 1 over the hull's edges
    and its corners other than q (Brianchon-Gram for the hull; q's own wedge cancels). The cell
    does not hold q, but q may lie on its boundary.
    """
    for i in range(4):  # on a corner up to round-off: exactly there, so no edge has a noise direction
        if math.hypot(px[i] - qx, py[i] - qy) < 1e-9 * radius:
            qx, qy = px[i], py[i]
    back = np.empty(4, dtype=np.bool_)  # edges that face away from q (q on their inner side)
    n_back = 0
    nearest, nearest_dist = 0, np.inf
    for i in range(4):
        j = (i + 1) % 4
        ex, ey = px[j] - px[i], py[j] - py[i]
        cross = ex * (qy - py[i]) - ey * (qx - px[i])
        back[i] = cross >= 0.0
        n_back += back[i]
        if cross / math.hypot(ex, ey) < nearest_dist:
            nearest, nearest_dist = i, cross / math.hypot(ex, ey)
    if n_back == 4:  # q on the boundary (round-off put it inside): the edge through it faces q
        back[nearest] = False
    start = 0
    while not (back[start] and not back[(start + 3) % 4]):
        start += 1
    total = -1.0
    prev_x, prev_y = qx, qy
    i = start
    while True:
        j = (i + 1) % 4
        next_x, next_y = (px[j], py[j]) if back[i] else (qx, qy)
        total += _halfplane_mass(prev_x, prev_y, px[i], py[i])
        total -= _corner_mass(px[i], py[i], next_x, next_y, prev_x, prev_y)
        if not back[i]:
            total += _halfplane_mass(px[i], py[i], qx, qy)
            break
        prev_x, prev_y = px[i], py[i]
        i = j
    return max(total, 0.0)


@njit(cache=True)
def _beyond_2d(qx, qy, px, py, ccx, ccy, radius):
    """Mass beyond the cell on rays from q (isotropic frame, component N(0, I)); Eq. 5 where exact."""
    p = math.hypot(qx, qy)
    if p >= NEGLIGIBLE_SIGMA + 1.0:
        # Rotate the sensor -> mean direction onto the x-axis (Sec. III-C): depth and lateral offset.
        bx, by = -qx / p, -qy / p
        all_front, all_back = True, True
        sin1, sin2, r_far = 1.0, -1.0, 0.0
        for i in range(4):
            wx, wy = px[i] - qx, py[i] - qy
            r = math.hypot(wx, wy)
            if r < 1e-9 * radius:  # the sensor on a corner: its angle is round-off
                return _beyond_exact_2d(qx, qy, px, py, radius)
            if wx * bx + wy * by > 0.0:
                all_back = False
            else:
                all_front = False
            s = (bx * wy - by * wx) / r
            sin1, sin2, r_far = min(sin1, s), max(sin2, s), max(r_far, r)
        if all_back:  # the wedge points away from the component
            return 0.0
        if all_front:
            if (sin1 > 0.0 and p * sin1 > NEGLIGIBLE_SIGMA) or (sin2 < 0.0 and -p * sin2 > NEGLIGIBLE_SIGMA):
                return 0.0  # the wedge passes the component by
            if math.hypot(ccx - qx, ccy - qy) - radius > p + NEGLIGIBLE_SIGMA:
                return 0.0  # the cell lies behind the component
            if r_far < p - NEGLIGIBLE_SIGMA:
                return _eq5(p, sin1, sin2, r_far)  # exact to 1e-10: nothing between q and the cell
    return _beyond_exact_2d(qx, qy, px, py, radius)


@njit(cache=True)
def _cell_evidence_2d(mean, cov, iso, sensor, max_range, cx, cy, half, px, py):
    """(hits, misses) of one component in one square cell, as fractions of its mass."""
    for i in range(4):  # corners, counter-clockwise, in the isotropic frame
        dx = cx + (half if i == 1 or i == 2 else -half) - mean[0]
        dy = cy + (half if i >= 2 else -half) - mean[1]
        px[i] = iso[0, 0] * dx + iso[0, 1] * dy
        py[i] = iso[1, 0] * dx + iso[1, 1] * dy
    _make_ccw(px, py, 4)
    ccx = iso[0, 0] * (cx - mean[0]) + iso[0, 1] * (cy - mean[1])
    ccy = iso[1, 0] * (cx - mean[0]) + iso[1, 1] * (cy - mean[1])
    radius = 0.0
    for i in range(4):
        radius = max(radius, math.hypot(px[i] - ccx, py[i] - ccy))
    mass = 0.0
    if math.hypot(ccx, ccy) - radius < NEGLIGIBLE_SIGMA + 1.0:
        mass = _rect_mass_2d(mean, cov, cx, cy, half)
    if _holds_sensor(sensor, (cx, cy), half):
        beyond = 1.0 - mass
    else:
        qx = iso[0, 0] * (sensor[0] - mean[0]) + iso[0, 1] * (sensor[1] - mean[1])
        qy = iso[1, 0] * (sensor[0] - mean[0]) + iso[1, 1] * (sensor[1] - mean[1])
        beyond = _beyond_2d(qx, qy, px, py, ccx, ccy, radius)
    if max_range:
        return 0.0, beyond + mass
    return mass, beyond


# ---------------------------------------------------------------------------------------------
# 3D: one component, one cube
# ---------------------------------------------------------------------------------------------

SLICE_HALF_WIDTH = 9.0  # slices are clipped to |u|, |v| <= 9 (isotropic): the mass outside is < 1e-18


@njit(cache=True)
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def _sort_small(values, n):
    """Insertion sort of values[:n] in place (n <= 11; numba's sort costs seconds to compile)."""
    for i in range(1, n):
        v = values[i]
        j = i - 1
        while j >= 0 and values[j] > v:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = v


@njit(cache=True)
def _cube_corners(cx, cy, cz, half):
    """The 8 corners; bit a of the index set means the upper side along axis a."""
    corners = np.empty((8, 3))
    for k in range(8):
        corners[k, 0] = cx + (half if k & 1 else -half)
        corners[k, 1] = cy + (half if k & 2 else -half)
        corners[k, 2] = cz + (half if k & 4 else -half)
    return corners


@njit(cache=True)
def _cube_halfspaces(corners, sensor, normals, offsets):
    """Rows normals[i] . x >= offsets[i]: rows 0-5 the cube; from row 6 on, the region beyond the
    cube's entry seen from the sensor, C(V) = (cone from the sensor over the cube) cut by the far
    sides of the faces the sensor sees. Returns the number of rows of C(V)."""
    front = np.zeros((3, 2), dtype=np.bool_)
    for a in range(3):
        for side in range(2):
            row = 2 * a + side
            normals[row, :] = 0.0
            normals[row, a] = -1.0 if side else 1.0
            offsets[row] = -corners[7, a] if side else corners[0, a]
        front[a, 0] = sensor[a] <= corners[0, a]  # a sensor on the face's plane sees it too
        front[a, 1] = sensor[a] >= corners[7, a]
    n = 6
    for a in range(3):
        for side in range(2):
            if front[a, side]:  # the far side of a visible face is the cube's own half-space
                normals[n, :] = normals[2 * a + side]
                offsets[n] = offsets[2 * a + side]
                n += 1
    for a in range(3):  # silhouette edges (one adjacent face seen, the other not): cone facets
        u, v = (a + 1) % 3, (a + 2) % 3
        for bu in range(2):
            for bv in range(2):
                if front[u, bu] == front[v, bv]:
                    continue
                k = (bu << u) | (bv << v)
                e0, e1 = corners[k], corners[k | (1 << a)]
                g0 = (e0[1] - sensor[1]) * (e1[2] - sensor[2]) - (e0[2] - sensor[2]) * (e1[1] - sensor[1])
                g1 = (e0[2] - sensor[2]) * (e1[0] - sensor[0]) - (e0[0] - sensor[0]) * (e1[2] - sensor[2])
                g2 = (e0[0] - sensor[0]) * (e1[1] - sensor[1]) - (e0[1] - sensor[1]) * (e1[0] - sensor[0])
                norm = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                if norm < 1e-9 * (corners[7, 0] - corners[0, 0]) ** 2:
                    continue  # the edge's line runs through the sensor: its neighbours bound the cone
                inward = (g0 * (0.5 * (corners[0, 0] + corners[7, 0]) - sensor[0])  # towards the centre
                          + g1 * (0.5 * (corners[0, 1] + corners[7, 1]) - sensor[1])
                          + g2 * (0.5 * (corners[0, 2] + corners[7, 2]) - sensor[2]))
                scale = (1.0 if inward >= 0.0 else -1.0) / norm
                normals[n, 0], normals[n, 1], normals[n, 2] = g0 * scale, g1 * scale, g2 * scale
                offsets[n] = _dot3(normals[n], sensor)
                n += 1
    return n - 6


@njit(cache=True)
def _clipped_slice_mass(alpha, beta, gamma, first, count, xa, ya, xb, yb):
    """Exact standard normal mass of {(u, v): alpha u + beta v >= gamma} over rows first..first+count,
    clipped to the square |u|, |v| <= SLICE_HALF_WIDTH (Sutherland-Hodgman, then Brianchon-Gram)."""
    w = SLICE_HALF_WIDTH
    xa[0], ya[0], xa[1], ya[1], xa[2], ya[2], xa[3], ya[3] = -w, -w, w, -w, w, w, -w, w
    n = 4
    for i in range(first, first + count):
        m = 0
        for j in range(n):
            k = (j + 1) % n
            fj = alpha[i] * xa[j] + beta[i] * ya[j] - gamma[i]
            fk = alpha[i] * xa[k] + beta[i] * ya[k] - gamma[i]
            if fj >= 0.0:
                xb[m], yb[m] = xa[j], ya[j]
                m += 1
            if (fj >= 0.0) != (fk >= 0.0):
                f = fj / (fj - fk)
                xb[m], yb[m] = xa[j] + f * (xa[k] - xa[j]), ya[j] + f * (ya[k] - ya[j])
                m += 1
        if m < 3:
            return 0.0
        n = m
        for j in range(n):
            xa[j], ya[j] = xb[j], yb[j]
    return _polygon_mass_exact(xa, ya, n)


@njit(cache=True)
def _cube_masses_3d(mean, evals, evecs, sensor, corners, with_cone):
    """(mass of the cube (Eq. 10), mass of C(V) (Eq. 3 plus the cube)), by slices across the thinnest axis.

    In the eigenbasis the offset z along the thinnest eigenvector is independent of the in-plane
    coordinates, so each mass is the integral over z of the exact mass of a convex slice (Eq. 10
    for the cube). The slices change shape only at the corners' offsets: Gauss-Legendre runs
    between them, in t = Phi(z / sigma) so that the Gaussian weight is absorbed.
    """
    normals = np.empty((16, 3))
    offsets = np.empty(16)
    n_cone = _cube_halfspaces(corners, sensor, normals, offsets)  # fills the cube's rows too
    if not with_cone:
        n_cone = 0
    rows = 6 + n_cone
    sn = math.sqrt(evals[0])
    alpha, beta = np.empty(rows), np.empty(rows)
    gamma0, gamma1, gamma = np.empty(rows), np.empty(rows), np.empty(rows)
    for i in range(rows):  # a row in slice coordinates: alpha u + beta v >= gamma0 - z gamma1
        alpha[i], beta[i], gamma0[i], gamma1[i] = 0.0, 0.0, offsets[i], 0.0
        for j in range(3):
            alpha[i] += math.sqrt(evals[1]) * normals[i, j] * evecs[j, 1]
            beta[i] += math.sqrt(evals[2]) * normals[i, j] * evecs[j, 2]
            gamma0[i] -= normals[i, j] * mean[j]
            gamma1[i] += normals[i, j] * evecs[j, 0]
    breaks = np.empty(11)
    for k in range(8):
        breaks[k] = 0.0
        for j in range(3):
            breaks[k] += evecs[j, 0] * (corners[k, j] - mean[j])
    z_lo, z_hi = breaks[:8].min(), breaks[:8].max()
    breaks[8] = 0.0
    breaks[9], breaks[10] = (-np.inf, np.inf) if with_cone else (z_lo, z_hi)
    _sort_small(breaks, 11)
    xa, ya, xb, yb = np.empty(32), np.empty(32), np.empty(32), np.empty(32)
    cube_mass, cone_mass = 0.0, 0.0
    for i in range(10):
        za, zb = breaks[i], breaks[i + 1]
        if not zb > za:
            continue
        sign = 1.0 if za + zb > 0.0 or zb == np.inf else -1.0  # upper half: t = Q(z/sn); lower: Phi
        ta, tb = _norm_sf(sign * za / sn), _norm_sf(sign * zb / sn)
        width = abs(tb - ta)
        if width < 1e-16:
            continue
        in_cube = za >= z_lo and zb <= z_hi
        for g in range(_SLICE_X.shape[0]):
            z = -sign * sn * _norm_ppf_lower(min(ta, tb) + 0.5 * width * (_SLICE_X[g] + 1.0))
            weight = 0.5 * width * _SLICE_W[g]
            for r in range(rows):
                gamma[r] = gamma0[r] - z * gamma1[r]
            if in_cube:
                cube_mass += weight * _clipped_slice_mass(alpha, beta, gamma, 0, 6, xa, ya, xb, yb)
            if with_cone:
                cone_mass += weight * _clipped_slice_mass(alpha, beta, gamma, 6, n_cone, xa, ya, xb, yb)
    return min(cube_mass, 1.0), min(max(cone_mass, cube_mass), 1.0)


@njit(cache=True)
def _convex_hull(xs, ys, n, hull):
    """The convex hull of n points, counter-clockwise, into hull; returns its size (monotone chain)."""
    order = np.arange(n)
    for i in range(1, n):  # insertion sort by (x, y)
        j = i
        while j > 0 and (xs[order[j - 1]] > xs[order[j]]
                         or (xs[order[j - 1]] == xs[order[j]] and ys[order[j - 1]] > ys[order[j]])):
            order[j - 1], order[j] = order[j], order[j - 1]
            j -= 1
    m = 0
    for rep in range(2):
        start = m
        for j in range(n):
            i = order[j] if rep == 0 else order[n - 1 - j]
            while m - start >= 2:
                a, b = hull[m - 2], hull[m - 1]
                if (xs[b] - xs[a]) * (ys[i] - ys[a]) - (ys[b] - ys[a]) * (xs[i] - xs[a]) > 0.0:
                    break
                m -= 1
            hull[m] = i
            m += 1
        m -= 1  # the last point of each chain starts the other
    return m


@njit(cache=True)
def _shadow_mass_eq9(ws, b, p):
    """Eq. 6-9: mass of the cube's shadow, cast from the sensor onto the plane through the mean
    across the beam (isotropic frame; ws: corners relative to the sensor, all in front of it)."""
    t1 = np.array([-b[1], b[0], 0.0]) if abs(b[2]) < 0.9 else np.array([0.0, -b[2], b[1]])
    t1 /= math.sqrt(_dot3(t1, t1))
    t2 = np.array([b[1] * t1[2] - b[2] * t1[1], b[2] * t1[0] - b[0] * t1[2], b[0] * t1[1] - b[1] * t1[0]])
    xs, ys = np.empty(8), np.empty(8)
    for k in range(8):
        scale = p / _dot3(ws[k], b)
        xs[k] = _dot3(ws[k], t1) * scale
        ys[k] = _dot3(ws[k], t2) * scale
    hull = np.empty(16, dtype=np.int64)
    m = _convex_hull(xs, ys, 8, hull)
    hx, hy = np.empty(m), np.empty(m)
    for i in range(m):
        hx[i], hy[i] = xs[hull[i]], ys[hull[i]]
    return _polygon_mass_eq9(hx, hy, m)


@njit(cache=True)
def _cell_evidence_3d(mean, evals, evecs, iso, sensor, max_range, cx, cy, cz, half):
    """(hits, misses) of one component in one cube, as fractions of its mass."""
    corners = _cube_corners(cx, cy, cz, half)
    if _holds_sensor(sensor, (cx, cy, cz), half):
        mass = _cube_masses_3d(mean, evals, evecs, sensor, corners, False)[0]
        return (0.0, 1.0) if max_range else (mass, 1.0 - mass)
    # Isotropic frame, sensor at the origin: q is the sensor seen from the mean, ws the corners.
    q = np.zeros(3)
    centre = np.zeros(3)
    ws = np.zeros((8, 3))
    for i in range(3):
        for j in range(3):
            q[i] += iso[i, j] * (sensor[j] - mean[j])
            centre[i] += iso[i, j] * ((cx, cy, cz)[j] - sensor[j])
            for k in range(8):
                ws[k, i] += iso[i, j] * (corners[k, j] - sensor[j])
    p = math.sqrt(_dot3(q, q))
    dist = math.sqrt(_dot3(centre, centre))
    radius, r_far, all_front = 0.0, 0.0, p > 0.0
    for k in range(8):
        offset = ws[k] - centre
        radius = max(radius, math.sqrt(_dot3(offset, offset)))
        r_far = max(r_far, math.sqrt(_dot3(ws[k], ws[k])))
        all_front = all_front and _dot3(ws[k], q) < 0.0
    if dist - radius > p + NEGLIGIBLE_SIGMA:
        return 0.0, 0.0  # behind the component
    if p > NEGLIGIBLE_SIGMA + 1.0:
        b = -q / p
        if dist > radius and (math.acos(min(1.0, max(-1.0, _dot3(centre, b) / dist)))
                              > math.asin(radius / dist) + math.asin(NEGLIGIBLE_SIGMA / p)):
            return 0.0, 0.0  # the cube's cone passes the component by
        if all_front and r_far < p - NEGLIGIBLE_SIGMA:
            return 0.0, _shadow_mass_eq9(ws, b, p)  # well in front: the paper's Eq. 9
    mass, beyond_entry = _cube_masses_3d(mean, evals, evecs, sensor, corners, True)
    return (0.0, beyond_entry) if max_range else (mass, max(beyond_entry - mass, 0.0))


# ---------------------------------------------------------------------------------------------
# Batches: many cells, many components
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _may_reach(cell, rho, sensor, mean, axis, dist_mean, reach, half_angle):
    """Whether a cell (centre, bounding radius rho) may meet the rays from the sensor to the ball
    of radius `reach` around the component's mean: it must meet their box, and the cone from the
    sensor over the ball, before its far side. Cheap culling."""
    for i in range(cell.shape[0]):
        if (cell[i] < min(sensor[i], mean[i] - reach) - rho
                or cell[i] > max(sensor[i], mean[i] + reach) + rho):
            return False
    dist_sq = 0.0
    along = 0.0
    for i in range(cell.shape[0]):
        d = cell[i] - sensor[i]
        dist_sq += d * d
        along += d * axis[i]
    dist = math.sqrt(dist_sq)
    if dist > dist_mean + reach + rho:
        return False
    if dist <= rho * (1.0 + 1e-9) or dist_mean <= reach:  # the cell may hold the sensor
        return True
    opening = half_angle + math.asin(rho / dist)
    return opening >= math.pi or along >= dist * math.cos(opening)


@njit(cache=True, parallel=True)
def _evidence_at_cells(centers, half, means, covs, isos, evals, evecs, sensors, max_range, counts,
                       axes, dist_means, reaches, half_angles):
    """Expected hits and misses at each cell from every component that may reach it."""
    n_cells, dim = centers.shape
    hits = np.zeros(n_cells)
    misses = np.zeros(n_cells)
    rho = half * math.sqrt(dim)
    for c in prange(n_cells):
        fx = np.empty(4)
        fy = np.empty(4)
        cell = centers[c]
        for k in range(means.shape[0]):
            if not _may_reach(cell, rho, sensors[k], means[k], axes[k], dist_means[k], reaches[k], half_angles[k]):
                continue
            if dim == 2:
                h, m = _cell_evidence_2d(means[k], covs[k], isos[k], sensors[k], max_range[k],
                                         cell[0], cell[1], half, fx, fy)
            else:
                h, m = _cell_evidence_3d(means[k], evals[k], evecs[k], isos[k], sensors[k], max_range[k],
                                         cell[0], cell[1], cell[2], half)
            hits[c] += counts[k] * h
            misses[c] += counts[k] * m
    return hits, misses


@njit(cache=True, parallel=True)
def _map_2d(grid_origin, resolution, nx, ny, means, covs, isos, sensors, max_range, counts,
            axes, dist_means, reaches, half_angles, n_chunks):
    """Expected hits and misses on a 2D grid: each component visits the cells of its cone's box.

    Components are dealt round-robin to n_chunks workers, each adding into its own copy of the
    counts (counts are additive), summed at the end.
    """
    acc_hits = np.zeros((n_chunks, ny, nx))
    acc_misses = np.zeros((n_chunks, ny, nx))
    half = 0.5 * resolution
    rho = half * math.sqrt(2.0)
    for chunk in prange(n_chunks):
        fx = np.empty(4)
        fy = np.empty(4)
        cell = np.empty(2)
        for k in range(chunk, means.shape[0], n_chunks):
            s, mu, r = sensors[k], means[k], reaches[k]
            # Every cell _may_reach accepts: centres within rho of the box of sensor and ball.
            lo_x = int(math.floor((min(s[0], mu[0] - r) - rho - grid_origin[0]) / resolution))
            hi_x = int(math.floor((max(s[0], mu[0] + r) + rho - grid_origin[0]) / resolution))
            lo_y = int(math.floor((min(s[1], mu[1] - r) - rho - grid_origin[1]) / resolution))
            hi_y = int(math.floor((max(s[1], mu[1] + r) + rho - grid_origin[1]) / resolution))
            for iy in range(max(lo_y, 0), min(hi_y, ny - 1) + 1):
                cell[1] = grid_origin[1] + (iy + 0.5) * resolution
                for ix in range(max(lo_x, 0), min(hi_x, nx - 1) + 1):
                    cell[0] = grid_origin[0] + (ix + 0.5) * resolution
                    if not _may_reach(cell, rho, s, mu, axes[k], dist_means[k], r, half_angles[k]):
                        continue
                    h, m = _cell_evidence_2d(mu, covs[k], isos[k], s, max_range[k], cell[0], cell[1], half, fx, fy)
                    acc_hits[chunk, iy, ix] += counts[k] * h
                    acc_misses[chunk, iy, ix] += counts[k] * m
    return acc_hits.sum(axis=0), acc_misses.sum(axis=0)


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------

def _isotropic_maps(covs: np.ndarray):
    """Sigma = V S V^T (ascending S), with S floored so that a singular Sigma stays usable, and the
    isotropic map S^-1/2 V^T (Sec. III-C). Returns (Sigma rebuilt from the floored S, S, V, map)."""
    evals, evecs = np.linalg.eigh(covs)
    evals = np.maximum(evals, np.maximum(evals[..., -1:] * 1e-14, 1e-300))
    covs = (evecs * evals[..., None, :]) @ np.swapaxes(evecs, -1, -2)
    isos = np.swapaxes(evecs, -1, -2) / np.sqrt(evals)[..., :, None]
    return np.ascontiguousarray(covs), evals, np.ascontiguousarray(evecs), np.ascontiguousarray(isos)


def _as_cells(centers, cell_size: float, dim: int) -> tuple[np.ndarray, float]:
    centers = np.asarray(centers, dtype=np.float64)
    if centers.shape[-1] != dim:
        raise ValueError(f"centers are {centers.shape[-1]}D points, the component or scans are {dim}D")
    centers = np.ascontiguousarray(centers.reshape(-1, dim))
    if not (np.isfinite(cell_size) and cell_size > 0):
        raise ValueError(f"cell_size must be positive, got {cell_size}")
    return centers, 0.5 * float(cell_size)


def component_evidence(mean, cov, origin, centers, cell_size: float, *,
                       max_range: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Hits and misses one Gaussian component gives each cell, as fractions of its mass.

    mean (d,), cov (d, d), origin (d,): the sensor; centers (M, d), cell_size: axis-aligned
    squares (d = 2) or cubes (d = 3). Hits are Eq. 10 (zero for a max-range component); misses
    the mass beyond the cell on rays from the origin (Eq. 3-9), plus the mass inside the cell
    for a max-range component. Multiply by N pi_k for expected counts.
    """
    mean = np.asarray(mean, dtype=np.float64).reshape(1, -1)
    cov = np.asarray(cov, dtype=np.float64).reshape(1, mean.shape[1], mean.shape[1])
    centers, half = _as_cells(centers, cell_size, mean.shape[1])
    cov, evals, evecs, isos = _isotropic_maps(cov)
    sensor = np.asarray(origin, dtype=np.float64).reshape(1, -1)
    everywhere = (np.ones_like(mean), np.zeros(1), np.full(1, np.inf), np.full(1, np.pi))  # no culling
    return _evidence_at_cells(centers, half, mean, cov, isos, evals, evecs, sensor, np.array([bool(max_range)]),
                              np.ones(1), *everywhere)


@numba.vectorize(["float64(float64, float64, float64, float64)"], cache=True)
def eq5(p, theta1, theta2, r_prime):
    """Eq. 5 as printed, a ufunc: the mass of N((p, 0), I) seen from the origin within angles
    theta1..theta2 beyond radius r'. It drops the first term of Eq. 4 and evaluates its erfc at
    theta = 0: exact to ~1e-10 for p > 8 and r' < p - 7, cruder near the component."""
    return _eq5(p, math.sin(theta1), math.sin(theta2), r_prime)


def eq5_geometry(mean, cov, origin, centers, cell_size: float):
    """The quantities of Eq. 5 for square cells seen from `origin`: (p, theta1, theta2, r').

    Isotropic map of the component, rotation of the sensor -> mean direction onto the x-axis
    with the sensor at the origin: p is the distance of the mean, theta1 <= theta2 bound the
    transformed cell as seen from the sensor, r' is the cell's closest radial distance.
    """
    mean = np.asarray(mean, dtype=np.float64)
    centers, half = _as_cells(centers, cell_size, 2)
    iso = _isotropic_maps(np.asarray(cov, dtype=np.float64))[3]
    q = iso @ (np.asarray(origin, dtype=np.float64) - mean)
    p = float(np.hypot(*q))
    beam = -q / p
    to_frame = np.array([beam, [-beam[1], beam[0]]])  # rows: x along the beam, y across
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
    corners = centers[:, None, :] + half * signs[None]  # (M, 4, 2), ccw
    local = (corners - mean) @ iso.T - q
    local = local @ to_frame.T
    angles = np.arctan2(local[..., 1], local[..., 0])
    theta1, theta2 = angles.min(axis=1), angles.max(axis=1)
    ends = np.roll(local, -1, axis=1)
    edge = ends - local
    t = np.clip(-(local * edge).sum(-1) / np.maximum((edge * edge).sum(-1), 1e-300), 0.0, 1.0)
    r_prime = np.linalg.norm(local + t[..., None] * edge, axis=-1).min(axis=1)
    return np.full(len(centers), p), theta1, theta2, r_prime


def polygon_mass(vertices, *, approximate: bool = False) -> float:
    """Standard bivariate normal mass of a convex polygon (corners (n, 2), either orientation).

    Exact (Brianchon-Gram over bivariate normal orthants), or with approximate=True Green's
    theorem with the erf approximation of Eq. 7 (Eq. 6-9; absolute error up to 0.012).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 2)
    xs, ys = v[:, 0].copy(), v[:, 1].copy()
    _make_ccw(xs, ys, len(v))
    return float((_polygon_mass_eq9 if approximate else _polygon_mass_exact)(xs, ys, len(v)))


@dataclass(frozen=True)
class _Components:
    """Every component of some scan models in the world frame (Eq. 2), with what culling needs."""

    means: np.ndarray  # (K, d)
    covs: np.ndarray  # (K, d, d)
    evals: np.ndarray  # (K, d) ascending
    evecs: np.ndarray  # (K, d, d) columns
    isos: np.ndarray  # (K, d, d) isotropic maps
    sensors: np.ndarray  # (K, d) sensor origin of each component's scan
    counts: np.ndarray  # (K,) N pi_k
    max_range: np.ndarray  # (K,) bool: from a free mixture
    axes: np.ndarray  # (K, d) unit sensor -> mean
    dist_means: np.ndarray  # (K,) |mean - sensor|
    reaches: np.ndarray  # (K,) REACH_SIGMA * largest sigma
    half_angles: np.ndarray  # (K,) half-angle of the cone from the sensor over the reach ball

    def cone(self):
        return self.axes, self.dist_means, self.reaches, self.half_angles


def _world_components(models_with_poses, dim: int) -> _Components:
    empty = (np.zeros((0, dim)), np.zeros((0, dim, dim)), np.zeros((0, dim)), np.zeros(0), np.zeros(0, bool))
    parts = [empty]  # (means, covariances, sensors, counts, max_range) per mixture
    for model, pose in models_with_poses:
        if model.dim != dim:
            raise ValueError(f"scan model is {model.dim}D, cells are {dim}D")
        sensor = pose.apply(model.origin[None])[0]
        for mixture, is_free in ((model.occupied, False), (model.free, True)):
            world = mixture.transformed(pose)
            parts.append((world.means, world.covariances, np.broadcast_to(sensor, world.means.shape),
                          world.support * world.weights, np.full(world.n_components, is_free)))
    means, covs, sensors, counts, max_range = (np.ascontiguousarray(np.concatenate(p)) for p in zip(*parts))
    covs, evals, evecs, isos = _isotropic_maps(covs)
    dist_means = np.linalg.norm(means - sensors, axis=1)
    axes = np.ascontiguousarray((means - sensors) / np.maximum(dist_means, 1e-300)[:, None])
    reaches = REACH_SIGMA * np.sqrt(evals[:, -1])
    half_angles = np.arcsin(np.minimum(reaches / np.maximum(dist_means, 1e-300), 1.0))
    return _Components(means, covs, evals, evecs, isos, sensors, counts, max_range, axes, dist_means,
                       reaches, half_angles)


def scan_evidence(models_with_poses, centers, cell_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Expected hit and miss counts (N_H, N_M of Eq. 11) at each cell from scan models with world
    poses, a list of (ScanModel, Pose). Only components whose 5-sigma cone reaches a cell count."""
    models_with_poses = list(models_with_poses)
    dim = models_with_poses[0][0].dim if models_with_poses else np.shape(centers)[-1]
    centers, half = _as_cells(centers, cell_size, dim)
    comp = _world_components(models_with_poses, dim)
    return _evidence_at_cells(centers, half, comp.means, comp.covs, comp.isos, comp.evals, comp.evecs,
                              comp.sensors, comp.max_range, comp.counts, *comp.cone())


def occupancy_at_cells(models_with_poses, centers, cell_size: float,
                       prior: float = DEFAULT_PRIOR) -> np.ndarray:
    """p(occupied) of each cell, Eq. 11, from the analytic evidence of scan models with world poses.

    models_with_poses: list of (ScanModel, Pose); centers (M, d); cell_size: side of the square
    or cube; prior: N_p. Local occupancy evaluation for a few cells, without a grid.
    """
    hits, misses = scan_evidence(models_with_poses, centers, cell_size)
    return map_estimate(hits, misses, prior)


def analytic_map_2d(models_with_poses, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Expected hit and miss counts over a 2D grid, the analytic counterpart of reconstruct().

    Returns float64 arrays of grid.array_shape ([iy, ix]); Eq. 11 (map_estimate) turns them
    into probabilities.
    """
    if grid.dim != 2:
        raise ValueError("analytic_map_2d: the grid must be 2D")
    comp = _world_components(models_with_poses, 2)
    ny, nx = grid.array_shape
    budget = 512 * 2**20  # bytes for the per-worker copies of the counts
    n_chunks = int(max(1, min(4 * numba.get_num_threads(), budget // (16 * nx * ny))))
    return _map_2d(grid.origin, grid.resolution, nx, ny, comp.means, comp.covs, comp.isos, comp.sensors,
                   comp.max_range, comp.counts, *comp.cone(), n_chunks)
