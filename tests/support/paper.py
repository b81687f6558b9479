"""The paper's formulas as printed, and Python entry points to kernels that only tests and benches
call: Eq. 5 on angles (the product's kernel takes their sines), the geometry that feeds it, and the
standard normal mass of one polygon, exact or by Eq. 6-9."""

from __future__ import annotations

import math

import numba
import numpy as np

from gmm_core.analytic.cells import as_cells
from gmm_core.analytic.components import isotropic_maps
from gmm_core.analytic.evidence_2d import eq5_by_sines
from gmm_core.analytic.evidence_3d import polygon_mass_eq9
from gmm_core.analytic.polygon import make_ccw, polygon_mass_exact


@numba.vectorize(["float64(float64, float64, float64, float64)"], cache=True)
def eq5_by_angles(p, theta1, theta2, r_prime):
    """Eq. 5 as printed, a ufunc: the mass of N((p, 0), I) seen from the origin within angles
    theta1..theta2 beyond radius r'. It drops the first term of Eq. 4 and evaluates its erfc at
    theta = 0: exact to ~1e-10 for p > 8 and r' < p - 7, cruder near the component."""
    return eq5_by_sines(p, math.sin(theta1), math.sin(theta2), r_prime)


def eq5_geometry(mean, cov, origin, centers, cell_size: float):
    """The quantities of Eq. 5 for square cells seen from `origin`: (p, theta1, theta2, r').

    Isotropic map of the component, rotation of the sensor -> mean direction onto the x-axis
    with the sensor at the origin: p is the distance of the mean, theta1 <= theta2 bound the
    transformed cell as seen from the sensor, r' is the cell's closest radial distance.
    """
    mean = np.asarray(mean, dtype=np.float64)
    centers, half = as_cells(centers, cell_size, 2)
    iso = isotropic_maps(np.asarray(cov, dtype=np.float64))[3]
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
    make_ccw(xs, ys, len(v))
    return float((polygon_mass_eq9 if approximate else polygon_mass_exact)(xs, ys, len(v)))
