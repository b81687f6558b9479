"""3D analytic evidence: the hits (Eq. 10) and misses (Eq. 3) of one component in one cube, and the
paper's approximate polygon mass (Eq. 6-9) that its misses use well in front of the component.

Hits: quadrature over slices across the component's thinnest axis, each slice an exact polygon
probability. Misses: well in front of the component the paper's Eq. 6-9 (the cube's shadow on
the plane through the mean across the beam, by Green's theorem with the erf approximation of
Eq. 7; error up to 0.012 of the component's mass); near it exactly, as the mass of C(V) = the
cone from the sensor over the cube beyond the cube's entry (a convex polyhedron) minus the
cube's own, by the same slices as the hits.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gmm_core.analytic.components import NEGLIGIBLE_SIGMA, holds_sensor
from gmm_core.analytic.polygon import polygon_mass_exact
from gmm_core.analytic.special import SQRT2, SQRT_2_OVER_PI, SQRT_2PI, SQRT_HALF_PI, erf_diff, norm_ppf_lower, norm_sf
from gmm_core.scan_trace import hit_stop

# Gauss-Legendre rule on [-1, 1] for the slices of a cube (_cube_masses_3d).
_SLICE_X, _SLICE_W = np.polynomial.legendre.leggauss(6)
# The rows of _cube_halfspaces: the cube's 6, then C(V)'s. numpy integers, not literals: numba
# would compile _clipped_slice_mass once for each literal it is called with (ARCHITECTURE.md).
_FIRST_CUBE_ROW, _FIRST_CONE_ROW = np.int64(0), np.int64(6)
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
                inward = (
                    g0 * (0.5 * (corners[0, 0] + corners[7, 0]) - sensor[0])  # towards the centre
                    + g1 * (0.5 * (corners[0, 1] + corners[7, 1]) - sensor[1])
                    + g2 * (0.5 * (corners[0, 2] + corners[7, 2]) - sensor[2])
                )
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
    return polygon_mass_exact(xa, ya, n)


@njit(cache=True)
def _cube_masses_3d(mean, evals, evecs, sensor, corners, with_cone, scale):
    """(mass of the cube (Eq. 10), mass of C(V) (Eq. 3 plus the cube), mass of both) of the
    component's samples x moved to sensor + `scale` (x - sensor), along their own rays, by slices
    across the thinnest axis; the cube's mass is that of x itself (the moved samples in the cube
    moved alike). A sample is a miss of the cube where its moved point lies in C(V) and it is not in
    the cube: the second mass less the third (with `scale` 1, the second less the first).

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
    moved = scale != 1.0
    centre = np.empty(3)  # the moved component's mean; its axes' sigmas are scale times the component's
    cube = np.empty((8, 3))  # the cube moved with the samples
    for j in range(3):
        centre[j] = sensor[j] + scale * (mean[j] - sensor[j])
        for k in range(8):
            cube[k, j] = sensor[j] + scale * (corners[k, j] - sensor[j])
        offsets[2 * j], offsets[2 * j + 1] = cube[0, j], -cube[7, j]
    sn = scale * math.sqrt(evals[0])
    alpha, beta = np.empty(rows), np.empty(rows)
    gamma0, gamma1, gamma = np.empty(rows), np.empty(rows), np.empty(rows)
    for i in range(rows):  # a row in slice coordinates: alpha u + beta v >= gamma0 - z gamma1
        alpha[i], beta[i], gamma0[i], gamma1[i] = 0.0, 0.0, offsets[i], 0.0
        for j in range(3):
            alpha[i] += scale * math.sqrt(evals[1]) * normals[i, j] * evecs[j, 1]
            beta[i] += scale * math.sqrt(evals[2]) * normals[i, j] * evecs[j, 2]
            gamma0[i] -= normals[i, j] * centre[j]
            gamma1[i] += normals[i, j] * evecs[j, 0]
    breaks = np.empty(19)
    for k in range(8):
        breaks[k], breaks[11 + k] = 0.0, 0.0
        for j in range(3):
            breaks[k] += evecs[j, 0] * (cube[k, j] - centre[j])
            breaks[11 + k] += evecs[j, 0] * (corners[k, j] - centre[j])  # C(V)'s edges, where the cube moved
    z_lo, z_hi = breaks[:8].min(), breaks[:8].max()
    breaks[8] = 0.0
    breaks[9], breaks[10] = (-np.inf, np.inf) if with_cone else (z_lo, z_hi)
    n_breaks = 19 if moved and with_cone else 11
    _sort_small(breaks, n_breaks)
    xa, ya, xb, yb = np.empty(32), np.empty(32), np.empty(32), np.empty(32)
    cube_mass, cone_mass, both_mass = 0.0, 0.0, 0.0
    for i in range(n_breaks - 1):
        za, zb = breaks[i], breaks[i + 1]
        if not zb > za:
            continue
        sign = 1.0 if za + zb > 0.0 or zb == np.inf else -1.0  # upper half: t = Q(z/sn); lower: Phi
        ta, tb = norm_sf(sign * za / sn), norm_sf(sign * zb / sn)
        width = abs(tb - ta)
        if width < 1e-16:
            continue
        in_cube = za >= z_lo and zb <= z_hi
        for g in range(_SLICE_X.shape[0]):
            z = -sign * sn * norm_ppf_lower(min(ta, tb) + 0.5 * width * (_SLICE_X[g] + 1.0))
            weight = 0.5 * width * _SLICE_W[g]
            for r in range(rows):
                gamma[r] = gamma0[r] - z * gamma1[r]
            if in_cube:
                cube_mass += weight * _clipped_slice_mass(
                    alpha, beta, gamma, _FIRST_CUBE_ROW, _FIRST_CONE_ROW, xa, ya, xb, yb
                )
                if with_cone and moved:
                    both_mass += weight * _clipped_slice_mass(
                        alpha, beta, gamma, _FIRST_CUBE_ROW, np.int64(rows), xa, ya, xb, yb
                    )
            if with_cone:
                cone_mass += weight * _clipped_slice_mass(alpha, beta, gamma, _FIRST_CONE_ROW, n_cone, xa, ya, xb, yb)
    cube_mass = min(cube_mass, 1.0)
    both_mass = min(both_mass, cube_mass) if moved else cube_mass  # unmoved, the cube lies in C(V)
    return cube_mass, min(max(cone_mass, both_mass), 1.0), both_mass


@njit(cache=True)
def _convex_hull(xs, ys, n, hull):
    """The convex hull of n points, counter-clockwise, into hull; returns its size (monotone chain)."""
    order = np.arange(n)
    for i in range(1, n):  # insertion sort by (x, y)
        j = i
        while j > 0 and (
            xs[order[j - 1]] > xs[order[j]] or (xs[order[j - 1]] == xs[order[j]] and ys[order[j - 1]] > ys[order[j]])
        ):
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
def edge_piece_eq8(x0, y0, x1, y1, s):
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
    gauss = peak * erf_diff(-ra * shift, ra * (dx - shift))
    return s * (SQRT_HALF_PI * erf_diff(x0 / SQRT2, x1 / SQRT2) - gauss)


@njit(cache=True)
def polygon_mass_eq9(xs, ys, n):
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
            total += edge_piece_eq8(x0, y0, xz, 0.0, 1.0 if y0 > 0.0 else -1.0)
            total += edge_piece_eq8(xz, 0.0, x1, y1, 1.0 if y1 > 0.0 else -1.0)
        else:
            total += edge_piece_eq8(x0, y0, x1, y1, 1.0 if y0 + y1 >= 0.0 else -1.0)
    return min(max(-total / math.sqrt(8.0 * math.pi), 0.0), 1.0)


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
    return polygon_mass_eq9(hx, hy, m)


@njit(cache=True)
def cell_evidence_3d(mean, evals, evecs, iso, sensor, max_range, cx, cy, cz, half):
    """(hits, misses) of one component in one cube, as fractions of its mass. An occupied component's
    sample claims free only what its ray crosses until hit_stop short of it (gmm_core.scan_trace: a
    cube, or three of the component's thinnest standard deviations where that is farther): its misses
    are those of its point moved that stop toward the sensor along its ray, taken as the scaling
    about the sensor that moves a point at the cube's distance plus the stop by exactly the stop
    (the samples that a stop decides for the cube lie there; it errs where a component lies within
    about its stop of the sensor, nearer than a range sensor returns: 0.090 of a component's mass in
    a cube at the sensor, the component 0.33 m away with a 0.3 m stop). The cube
    that holds the sensor is crossed by every ray: all the mass outside it is its misses (the tracer
    leaves out the samples within the stop of the sensor, where a range sensor returns nothing)."""
    corners = _cube_corners(cx, cy, cz, half)
    if holds_sensor(sensor, (cx, cy, cz), half):
        mass = _cube_masses_3d(mean, evals, evecs, sensor, corners, np.bool_(False), 1.0)[0]
        return (0.0, 1.0) if max_range else (mass, 1.0 - mass)
    to_cube = math.sqrt((cx - sensor[0]) ** 2 + (cy - sensor[1]) ** 2 + (cz - sensor[2]) ** 2)
    scale = 1.0 if max_range else to_cube / (to_cube + hit_stop(2.0 * half, math.sqrt(evals[0])))
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
        if dist > radius and (
            math.acos(min(1.0, max(-1.0, _dot3(centre, b) / dist)))
            > math.asin(radius / dist) + math.asin(NEGLIGIBLE_SIGMA / p)
        ):
            return 0.0, 0.0  # the cube's cone passes the component by
        # The moved samples seen from the sensor in their own isotropic frame: q the same, the cube 1 / scale.
        if all_front and r_far / scale < p - NEGLIGIBLE_SIGMA:
            return 0.0, _shadow_mass_eq9(ws / scale, b, p)  # well in front: the paper's Eq. 9
    mass, beyond_entry, inside = _cube_masses_3d(mean, evals, evecs, sensor, corners, np.bool_(True), scale)
    return (0.0, beyond_entry) if max_range else (mass, max(beyond_entry - inside, 0.0))
