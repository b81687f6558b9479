"""2D analytic evidence: the hits (Eq. 10) and misses (Eq. 3, Eq. 5 where exact) of one component
in one square cell, and over a whole grid (analytic_map_2d, the product's analytic map).

Misses in the isotropic frame (component N(0, I), rays stay rays): Eq. 5 where it is exact to
1e-10 (the cell well in front of the component, the sensor well outside it); elsewhere exactly,
as the mass of the cell's wedge minus that of the convex hull of sensor and cell.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from gmm_core.analytic.components import NEGLIGIBLE_SIGMA, holds_sensor, may_reach, world_components
from gmm_core.analytic.polygon import corner_mass, halfplane_mass, make_ccw
from gmm_core.analytic.special import SQRT2, bvn_upper, erf_diff
from gmm_core.grid import Grid
from gmm_core.scan_trace import hit_stop


@njit(cache=True)
def eq5_by_sines(p, sin1, sin2, r_prime):
    """Eq. 5: 1/4 erfc((r' - p)/sqrt2) (erf(p sin(theta2)/sqrt2) - erf(p sin(theta1)/sqrt2)),
    given the sines sin1 = sin(theta1), sin2 = sin(theta2) (the caller has them without the angles).

    Mass of N((p, 0), I) seen from the origin in the wedge theta1..theta2 beyond radius r'.
    """
    return 0.25 * math.erfc((r_prime - p) / SQRT2) * erf_diff(p * sin1 / SQRT2, p * sin2 / SQRT2)


@njit(cache=True)
def _rect_mass_2d(mean, cov, x_lo, x_hi, y_lo, y_hi):
    """Eq. 10 over the rectangle [x_lo, x_hi] x [y_lo, y_hi] (none where empty): the bivariate normal
    rectangle probability (4 orthants)."""
    if not (x_hi > x_lo and y_hi > y_lo):
        return 0.0
    sx = math.sqrt(cov[0, 0])
    sy = math.sqrt(cov[1, 1])
    r = min(1.0, max(-1.0, cov[0, 1] / (sx * sy)))
    x0, x1 = (x_lo - mean[0]) / sx, (x_hi - mean[0]) / sx
    y0, y1 = (y_lo - mean[1]) / sy, (y_hi - mean[1]) / sy
    # Reflect so the cell lies on the upper side of each axis: tail masses keep their digits.
    if x0 + x1 < 0.0:
        x0, x1, r = -x1, -x0, -r
    if y0 + y1 < 0.0:
        y0, y1, r = -y1, -y0, -r
    mass = bvn_upper(x0, y0, r) - bvn_upper(x1, y0, r) - bvn_upper(x0, y1, r) + bvn_upper(x1, y1, r)
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
        total += halfplane_mass(prev_x, prev_y, px[i], py[i])
        total -= corner_mass(px[i], py[i], next_x, next_y, prev_x, prev_y)
        if not back[i]:
            total += halfplane_mass(px[i], py[i], qx, qy)
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
                return eq5_by_sines(p, sin1, sin2, r_far)  # exact to 1e-10: nothing between q and the cell
    return _beyond_exact_2d(qx, qy, px, py, radius)


@njit(cache=True)
def _square_in_iso(mean, iso, cx, cy, half, px, py):
    """The corners of the square of centre (cx, cy) and half side `half` in the component's isotropic
    frame (counter-clockwise, into px, py), and its centre and circumradius there."""
    for i in range(4):
        dx = cx + (half if i == 1 or i == 2 else -half) - mean[0]
        dy = cy + (half if i >= 2 else -half) - mean[1]
        px[i] = iso[0, 0] * dx + iso[0, 1] * dy
        py[i] = iso[1, 0] * dx + iso[1, 1] * dy
    make_ccw(px, py, 4)
    ccx = iso[0, 0] * (cx - mean[0]) + iso[0, 1] * (cy - mean[1])
    ccy = iso[1, 0] * (cx - mean[0]) + iso[1, 1] * (cy - mean[1])
    radius = 0.0
    for i in range(4):
        radius = max(radius, math.hypot(px[i] - ccx, py[i] - ccy))
    return ccx, ccy, radius


@njit(cache=True)
def _square_mass(mean, cov, cx, cy, half, ccx, ccy, radius):
    """Eq. 10 over the square (centre ccx, ccy and circumradius in the isotropic frame: _square_in_iso),
    none where it lies farther than NEGLIGIBLE_SIGMA from the component."""
    if math.hypot(ccx, ccy) - radius < NEGLIGIBLE_SIGMA + 1.0:
        return _rect_mass_2d(mean, cov, cx - half, cx + half, cy - half, cy + half)
    return 0.0


@njit(cache=True)
def cell_evidence_2d(mean, cov, iso, sensor, max_range, cx, cy, half, px, py):
    """(hits, misses) of one component in one square cell, as fractions of its mass. An occupied
    component's sample claims free only what its ray crosses until hit_stop short of it
    (gmm_core.scan_trace: a cell, or three of the component's thinnest standard deviations where that
    is farther), as in 3D (evidence_3d): its misses are those of its point moved that stop
    toward the sensor, taken as the scaling about the sensor that moves a point at the cell's
    distance plus the stop by exactly the stop. A moved point's ray crosses the cell where the point
    lies in the cell or beyond it, that is where the sample lies in the square scaled the other way
    (farther and larger) or beyond that; a sample in the cell is never its miss (its ray would leave
    the cell and enter it again), so the misses are the mass of the scaled square and beyond it, less
    that of its overlap with the cell. The cell that holds the sensor is crossed by every ray: all the
    mass outside it is its misses."""
    if holds_sensor(sensor, (cx, cy), half):
        mass = _rect_mass_2d(mean, cov, cx - half, cx + half, cy - half, cy + half)
        return (0.0, 1.0) if max_range else (mass, 1.0 - mass)
    qx = iso[0, 0] * (sensor[0] - mean[0]) + iso[0, 1] * (sensor[1] - mean[1])
    qy = iso[1, 0] * (sensor[0] - mean[0]) + iso[1, 1] * (sensor[1] - mean[1])
    ccx, ccy, radius = _square_in_iso(mean, iso, cx, cy, half, px, py)
    mass = _square_mass(mean, cov, cx, cy, half, ccx, ccy, radius)
    if max_range:
        return 0.0, mass + _beyond_2d(qx, qy, px, py, ccx, ccy, radius)
    # the component's thinnest variance, the smaller eigenvalue of its covariance
    thinnest = 0.5 * (cov[0, 0] + cov[1, 1]) - math.hypot(0.5 * (cov[0, 0] - cov[1, 1]), cov[0, 1])
    stop = hit_stop(2.0 * half, math.sqrt(max(thinnest, 0.0)))
    grow = 1.0 + stop / math.hypot(cx - sensor[0], cy - sensor[1])
    fx, fy, far_half = sensor[0] + grow * (cx - sensor[0]), sensor[1] + grow * (cy - sensor[1]), grow * half
    fcx, fcy, far_radius = _square_in_iso(mean, iso, fx, fy, far_half, px, py)
    far = _square_mass(mean, cov, fx, fy, far_half, fcx, fcy, far_radius) + _beyond_2d(
        qx, qy, px, py, fcx, fcy, far_radius
    )
    overlap = 0.0  # a part of the cell: none where the cell's own mass is
    if mass > 0.0:
        overlap = _rect_mass_2d(
            mean, cov, max(cx - half, fx - far_half), min(cx + half, fx + far_half), max(cy - half, fy - far_half),
            min(cy + half, fy + far_half),
        )  # fmt: skip
    return mass, max(far - overlap, 0.0)


@njit(cache=True, parallel=True)
def _map_2d(
    grid_origin,
    resolution,
    nx,
    ny,
    means,
    covs,
    isos,
    sensors,
    max_range,
    counts,
    axes,
    dist_means,
    reaches,
    half_angles,
    n_chunks,
):
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
            # Every cell may_reach accepts: centres within rho of the box of sensor and ball.
            lo_x = int(math.floor((min(s[0], mu[0] - r) - rho - grid_origin[0]) / resolution))
            hi_x = int(math.floor((max(s[0], mu[0] + r) + rho - grid_origin[0]) / resolution))
            lo_y = int(math.floor((min(s[1], mu[1] - r) - rho - grid_origin[1]) / resolution))
            hi_y = int(math.floor((max(s[1], mu[1] + r) + rho - grid_origin[1]) / resolution))
            for iy in range(max(lo_y, 0), min(hi_y, ny - 1) + 1):
                cell[1] = grid_origin[1] + (iy + 0.5) * resolution
                for ix in range(max(lo_x, 0), min(hi_x, nx - 1) + 1):
                    cell[0] = grid_origin[0] + (ix + 0.5) * resolution
                    if not may_reach(cell, rho, s, mu, axes[k], dist_means[k], r, half_angles[k]):
                        continue
                    h, m = cell_evidence_2d(mu, covs[k], isos[k], s, max_range[k], cell[0], cell[1], half, fx, fy)
                    acc_hits[chunk, iy, ix] += counts[k] * h
                    acc_misses[chunk, iy, ix] += counts[k] * m
    return acc_hits.sum(axis=0), acc_misses.sum(axis=0)


def analytic_map_2d(models_with_poses, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Expected hit and miss counts over a 2D grid, the analytic counterpart of reconstruct().

    Returns float64 arrays of grid.array_shape ([iy, ix]); Eq. 11 (map_estimate) turns them
    into probabilities.
    """
    if grid.dim != 2:
        raise ValueError("analytic_map_2d: the grid must be 2D")
    comp = world_components(models_with_poses, 2)
    ny, nx = grid.array_shape
    budget = 512 * 2**20  # bytes for the per-worker copies of the counts
    n_chunks = int(max(1, min(4 * numba.get_num_threads(), budget // (16 * nx * ny))))
    return _map_2d(
        grid.origin,
        grid.resolution,
        nx,
        ny,
        comp.means,
        comp.covs,
        comp.isos,
        comp.sensors,
        comp.max_range,
        comp.counts,
        *comp.cone(),
        n_chunks,
    )
