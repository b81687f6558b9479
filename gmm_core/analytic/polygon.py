"""Standard bivariate normal mass of convex polygons, exactly: Brianchon-Gram (corners - edges +
plane, one bivariate normal orthant per corner), and the pieces of it that the 2D wedge uses.
numba kernels. (The paper's approximate polygon mass, Eq. 6-9, serves the 3D path alone and
lives in evidence_3d.)"""

from __future__ import annotations

import math

from numba import njit

from gmm_core.analytic.special import bvn_upper, norm_sf


@njit(cache=True)
def halfplane_mass(ax, ay, bx, by):
    """Mass left of the directed line a -> b (the inner side of an edge of a ccw polygon)."""
    ex, ey = bx - ax, by - ay
    length = math.hypot(ex, ey)
    if length == 0.0:
        return 0.0
    return norm_sf((-ey * ax + ex * ay) / length)


@njit(cache=True)
def corner_mass(vx, vy, nx_, ny_, px, py):
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
    return bvn_upper(-d1y * vx + d1x * vy, d2y * vx - d2x * vy, rho)


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
def polygon_mass_exact(xs, ys, n):
    """Standard normal mass of a convex ccw polygon (Brianchon-Gram: corners - edges + plane)."""
    if n >= 3:
        n = _drop_repeated_corners(xs, ys, n)
    if n < 3:
        return 0.0
    total = 1.0
    for i in range(n):
        j = (i + 1) % n
        h = (i + n - 1) % n
        total += corner_mass(xs[i], ys[i], xs[j], ys[j], xs[h], ys[h])
        total -= halfplane_mass(xs[i], ys[i], xs[j], ys[j])
    return min(max(total, 0.0), 1.0)


@njit(cache=True)
def make_ccw(xs, ys, n):
    """Reverse a convex polygon's corners in place if they run clockwise."""
    area2 = 0.0
    for i in range(n):
        j = (i + 1) % n
        area2 += xs[i] * ys[j] - xs[j] * ys[i]
    if area2 < 0.0:
        for i in range(n // 2):
            xs[i], xs[n - 1 - i] = xs[n - 1 - i], xs[i]
            ys[i], ys[n - 1 - i] = ys[n - 1 - i], ys[i]
