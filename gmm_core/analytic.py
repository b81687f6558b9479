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
  sensor well outside it), elsewhere the exact mass of the cell's wedge minus the convex hull
  of sensor and cell, by Brianchon-Gram (one bivariate normal orthant per hull corner).
  3D (Eq. 6-9): the shadow of each exit face of the voxel, cast from the sensor onto the plane
  through the mean across the beam, integrated by Green's theorem with the erf approximation
  of Eq. 7, times the radial tail of Eq. 4 beyond that face.

What counts follows gmm_core.raytrace: a sample whose ray crosses the cell and ends outside it
is a miss of the cell; a sample inside the cell is a hit when it comes from the occupied mixture
and a miss when it comes from the free (max-range) mixture. A cell holding the sensor is crossed
by every ray.

Conventions: a cell is given by its centre and side (square in 2D, cube in 3D, axis-aligned);
masses are fractions of one component (multiply by N pi_k for counts).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from gmm_core.grid import Grid
from gmm_core.occupancy import DEFAULT_PRIOR, map_estimate
from gmm_core.pose import Pose
from gmm_core.scan import ScanModel

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
# Gauss-Legendre rule on [-1, 1] for the slices of a cube (box_mass_3d).
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
def _polygon_mass_exact(xs, ys, n):
    """Standard normal mass of a convex ccw polygon (Brianchon-Gram: corners - edges + plane)."""
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
    gauss = 0.5 * math.sqrt(math.pi / a) * math.exp(f0 + 0.25 * g0 * g0 / a) * _erf_diff(-ra * shift, ra * (dx - shift))
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
def _beyond_exact_2d(qx, qy, px, py, mass):
    """Mass of the cell's wedge from the sensor q beyond the cell (the ccw polygon px, py).

    wedge - hull(q, cell) = sum(edge half-planes) - sum(corner wedges) - 1 over the hull's edges
    and its corners other than q (Brianchon-Gram for the hull; q's own wedge cancels).
    """
    back = np.empty(4, dtype=np.bool_)  # edges that face away from q (q on their inner side)
    n_back = 0
    for i in range(4):
        j = (i + 1) % 4
        back[i] = (px[j] - px[i]) * (qy - py[i]) - (py[j] - py[i]) * (qx - px[i]) >= 0.0
        n_back += back[i]
    if n_back == 4:  # q inside the cell after round-off: every ray leaves through it
        return 1.0 - mass
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
def _beyond_2d(qx, qy, px, py, ccx, ccy, radius, mass):
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
    return _beyond_exact_2d(qx, qy, px, py, mass)


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
    if abs(sensor[0] - cx) <= half and abs(sensor[1] - cy) <= half:
        beyond = 1.0 - mass
    else:
        qx = iso[0, 0] * (sensor[0] - mean[0]) + iso[0, 1] * (sensor[1] - mean[1])
        qy = iso[1, 0] * (sensor[0] - mean[0]) + iso[1, 1] * (sensor[1] - mean[1])
        beyond = _beyond_2d(qx, qy, px, py, ccx, ccy, radius, mass)
    if max_range:
        return 0.0, beyond + mass
    return mass, beyond


# ---------------------------------------------------------------------------------------------
# 3D: one component, one cube
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _corner_offset(index, axis, half):
    return half if (index >> axis) & 1 else -half


@njit(cache=True)
def _slice_polygon(zs, us, vs, z, out_x, out_y):
    """The cube's section at normal offset z, as a ccw polygon in in-plane isotropic coordinates."""
    n = 0
    for a in range(8):
        for axis in range(3):
            b = a | (1 << axis)
            if b == a:
                continue
            za, zb = zs[a], zs[b]
            if za == zb or (za - z) * (zb - z) > 0.0:
                continue
            f = (z - za) / (zb - za)
            out_x[n] = us[a] + f * (us[b] - us[a])
            out_y[n] = vs[a] + f * (vs[b] - vs[a])
            n += 1
    if n < 3:
        return 0
    mx, my = out_x[:n].mean(), out_y[:n].mean()
    angles = np.arctan2(out_y[:n] - my, out_x[:n] - mx)
    order = np.argsort(angles)
    sx, sy = out_x[:n][order], out_y[:n][order]
    out_x[:n] = sx
    out_y[:n] = sy
    return n


@njit(cache=True)
def _box_mass_3d(mean, evals, evecs, cx, cy, cz, half, out_x, out_y):
    """Eq. 10 over a cube: integral over the offset z along the thinnest eigenvector of the exact
    mass of the cube's section (in-plane coordinates are independent of z in the eigenbasis),
    with Gauss-Legendre in the probability of z between the offsets of the cube's corners."""
    sn = math.sqrt(evals[0])
    s1 = math.sqrt(evals[1])
    s2 = math.sqrt(evals[2])
    zs = np.empty(9)
    us = np.empty(8)
    vs = np.empty(8)
    for k in range(8):
        d0 = cx + _corner_offset(k, 0, half) - mean[0]
        d1 = cy + _corner_offset(k, 1, half) - mean[1]
        d2 = cz + _corner_offset(k, 2, half) - mean[2]
        zs[k] = evecs[0, 0] * d0 + evecs[1, 0] * d1 + evecs[2, 0] * d2
        us[k] = (evecs[0, 1] * d0 + evecs[1, 1] * d1 + evecs[2, 1] * d2) / s1
        vs[k] = (evecs[0, 2] * d0 + evecs[1, 2] * d1 + evecs[2, 2] * d2) / s2
    zs[8] = min(max(0.0, zs[:8].min()), zs[:8].max())  # split at the mean: tails in their own terms
    breaks = np.sort(zs)
    total = 0.0
    for i in range(8):
        za, zb = breaks[i], breaks[i + 1]
        if zb <= za:
            continue
        # Lower half in t = Phi(z/sn), upper half in t = Q(z/sn): z = -+ sn Phi^-1(t).
        upper = za + zb > 0.0
        sign = 1.0 if upper else -1.0
        ta = _norm_sf(sign * za / sn)
        tb = _norm_sf(sign * zb / sn)
        width = abs(tb - ta)
        if width < 1e-16:
            continue
        for g in range(_SLICE_X.shape[0]):
            t = min(ta, tb) + 0.5 * width * (_SLICE_X[g] + 1.0)
            z = -sign * sn * _norm_ppf_lower(t)
            n = _slice_polygon(zs, us, vs, z, out_x, out_y)
            total += 0.5 * width * _SLICE_W[g] * _polygon_mass_exact(out_x, out_y, n)
    return min(total, 1.0)


@njit(cache=True)
def _face_shadow_eq9(ws, face, b, t1, t2, p, clip, fx, fy):
    """One cube face: the mass of its shadow, cast from the sensor onto the plane across the beam
    through the mean (Eq. 6-9), times the radial tail beyond the face (Eq. 4, inner integral).

    ws: the cube's corners relative to the sensor, isotropic frame; b: beam direction; t1, t2:
    across the beam. Parts of the face at depth <= 0 (beside or behind the sensor) are clipped:
    their rays never reach the plane.
    """
    depth_min = 1e-9 * max(p, 1.0)
    n = 0
    for i in range(4):
        a = face[i]
        c = face[(i + 1) % 4]
        da = ws[a] @ b
        dc = ws[c] @ b
        if da >= depth_min:
            clip[n] = ws[a]
            n += 1
        if (da >= depth_min) != (dc >= depth_min):
            clip[n] = ws[a] + (depth_min - da) / (dc - da) * (ws[c] - ws[a])
            n += 1
    if n < 3:
        return 0.0
    for i in range(n):
        scale = p / (clip[i] @ b)
        fx[i] = (clip[i] @ t1) * scale
        fy[i] = (clip[i] @ t2) * scale
    _make_ccw(fx, fy, n)
    shadow = _polygon_mass_eq9(fx, fy, n)
    centre = 0.25 * (ws[face[0]] + ws[face[1]] + ws[face[2]] + ws[face[3]])
    r_face = math.sqrt(centre @ centre)
    cos_theta = (centre @ b) / r_face
    return shadow * 0.5 * math.erfc((r_face - p * cos_theta) / SQRT2)


@njit(cache=True)
def _beyond_3d(iso, mean, sensor, cx, cy, cz, half, exit_faces, ws, clip, fx, fy):
    """Mass beyond the cube on rays from the sensor (exit_faces) or beyond its entry (not exit_faces)."""
    q = iso @ (sensor - mean)
    p = math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
    b = -q / p if p > 0.0 else np.array([1.0, 0.0, 0.0])
    t1 = np.array([-b[1], b[0], 0.0]) if abs(b[2]) < 0.9 else np.array([0.0, -b[2], b[1]])
    t1 /= math.sqrt(t1[0] ** 2 + t1[1] ** 2 + t1[2] ** 2)
    t2 = np.array([b[1] * t1[2] - b[2] * t1[1], b[2] * t1[0] - b[0] * t1[2], b[0] * t1[1] - b[1] * t1[0]])
    centre = iso @ (np.array([cx, cy, cz]) - mean) - q
    radius = 0.0
    for k in range(8):
        d = np.array([cx + _corner_offset(k, 0, half), cy + _corner_offset(k, 1, half),
                      cz + _corner_offset(k, 2, half)]) - mean
        ws[k] = iso @ d - q
        radius = max(radius, math.sqrt(((ws[k] - centre) ** 2).sum()))
    dist = math.sqrt((centre ** 2).sum())
    if dist - radius > p + NEGLIGIBLE_SIGMA:
        return 0.0  # behind the component
    if dist > radius and p > NEGLIGIBLE_SIGMA:
        off_axis = math.acos(min(1.0, max(-1.0, (centre @ b) / dist)))
        if off_axis > math.asin(radius / dist) + math.asin(NEGLIGIBLE_SIGMA / p):
            return 0.0  # the cube's cone passes the component by
    face = np.empty(4, dtype=np.int64)
    total = 0.0
    lo_hi = (cx - half, cy - half, cz - half, cx + half, cy + half, cz + half)
    for axis in range(3):
        for side in range(2):
            outward = sensor[axis] - lo_hi[axis + 3 * side] if side else lo_hi[axis] - sensor[axis]
            if outward == 0.0 or (outward < 0.0) != exit_faces:
                continue  # keep faces with the sensor on their inner side (exit) or outer side (entry)
            u, v = (axis + 1) % 3, (axis + 2) % 3
            base = side << axis
            face[0] = base
            face[1] = base | (1 << u)
            face[2] = base | (1 << u) | (1 << v)
            face[3] = base | (1 << v)
            total += _face_shadow_eq9(ws, face, b, t1, t2, p, clip, fx, fy)
    return min(total, 1.0)


@njit(cache=True)
def _cell_evidence_3d(mean, evals, evecs, iso, sensor, max_range, cx, cy, cz, half, ws, clip, fx, fy):
    """(hits, misses) of one component in one cube, as fractions of its mass."""
    centre = iso @ (np.array([cx, cy, cz]) - mean)
    reach = math.sqrt((centre ** 2).sum()) - math.sqrt(3.0) * half / math.sqrt(evals[0])
    mass = 0.0
    if reach < NEGLIGIBLE_SIGMA + 1.0:
        mass = _box_mass_3d(mean, evals, evecs, cx, cy, cz, half, fx, fy)
    if abs(sensor[0] - cx) <= half and abs(sensor[1] - cy) <= half and abs(sensor[2] - cz) <= half:
        return (0.0, 1.0) if max_range else (mass, 1.0 - mass)
    beyond = _beyond_3d(iso, mean, sensor, cx, cy, cz, half, not max_range, ws, clip, fx, fy)
    return (0.0, beyond) if max_range else (mass, beyond)
