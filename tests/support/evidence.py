"""The references the analytic evidence (gmm_core.analytic) is held to, shared by its tests:
Monte-Carlo counting of one cell as the ray tracer counts, and two small 2D scans of a corner."""

import numpy as np

from gmm_core import Mixture, Pose, ScanModel
from gmm_core.scan_trace import HIT_STOP_CELLS, HIT_STOP_SIGMAS


def hit_stop(cov, size):
    """How far short of an occupied sample of N(., cov) its misses stop on cells of `size` (m):
    HIT_STOP_CELLS cells, or HIT_STOP_SIGMAS of the thinnest standard deviation where that is more."""
    return max(HIT_STOP_CELLS * size, HIT_STOP_SIGMAS * np.sqrt(np.linalg.eigvalsh(cov)[0]))


def monte_carlo(mean, cov, origin, center, size, n, rng, max_range=False, stop=0.0):
    """(hit, miss) fractions of one cell, from n rays origin -> sample (slab test per ray); with
    `stop` (m), a sample's misses end that far short of it (gmm_core.scan_trace's occupied samples)."""
    x = rng.multivariate_normal(mean, cov, n)
    lo, hi = np.asarray(center) - size / 2, np.asarray(center) + size / 2
    o = np.asarray(origin, dtype=float)
    d = x - o
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = d * np.maximum(1.0 - stop / length, 0.0)  # a sample nearer than the stop: no ray of misses
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    inside_o = (o >= lo) & (o <= hi)
    t_enter = np.where(d != 0, np.minimum(ta, tb), np.where(inside_o, -np.inf, np.inf)).max(axis=1)
    t_exit = np.where(d != 0, np.maximum(ta, tb), np.where(inside_o, np.inf, -np.inf)).min(axis=1)
    crosses = (t_enter < t_exit) & (t_exit > 0) & (t_enter < 1) & np.any(d != 0, axis=1)  # a length inside
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    if max_range:
        return 0.0, crosses.mean()
    return inside.mean(), (crosses & ~inside).mean()


def two_scans_2d():
    """Two small scans of a corner, seen from two poses; every mixture has a free part too."""
    wall = Mixture(
        np.array([0.5, 0.5]),
        np.array([[2.0, -0.3], [2.0, 0.4]]),
        np.array([np.diag([1e-4, 0.04]), np.diag([2e-4, 0.02])]),
        40,
    )
    free = Mixture(np.ones(1), np.array([[0.5, 2.5]]), np.diag([0.05, 1e-4])[None], 10)
    scan = ScanModel(wall, free, np.zeros(2), 3.0)
    return [(scan, Pose.from_xytheta(0.0, 0.0, 0.0)), (scan, Pose.from_xytheta(0.3, -0.5, 0.2))]
