"""A spinning lidar's rings, read off a scan's elevation angles, and the footprint of its points
across them.

A spinning lidar samples a surface densely along each ring (azimuth steps of 0.1-0.4 deg) and
sparsely across them (1-3 deg): at range r a point stands for a strip about r * dphi wide between
its ring and the next. The voxel merge counts points (voxel_merge.py), so a group along one ring
stays thin across it and is cheap to extend along the ring: many components are ring segments, and
the rays traced to their samples run along the rings' cones, leaving the free space between them
barely seen (a few misses: p just under 0.5). Adding to each voxel the variance of its points'
footprint across the rings, (r dphi)^2 / 12 along the elevation direction (a uniform strip), lets
the costs see surface instead, and groups span the rings. The mine sim's region at 0.1 m went from
AUROC 0.980 to 0.993 (docs/BENCHMARKS.md, twenty-third session). The footprint enters the merge
costs only; the components are the points' own moments (in them too, it cost BALM 0.6 nats a point).

The rings are the clusters of the points' elevation angles in the sensor's frame that are narrower
than their spacing, the spacing the median gap between neighbouring ones; scans from sensors
without rings (a tilting 2D scanner, a depth camera, a lidar tilted in the scan's frame) show none
and get no footprint.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from gmm_core.selection import median

_BIN = np.radians(0.02)  # elevation histogram bins: narrower than a ring's spread (0.2-0.3 deg at BALM)
_RING_GAP = np.radians(0.2)  # a gap at least this wide between elevations separates two rings
_SAMPLE = 8192  # points whose elevation is read: about 130 a ring for 64 rings
# m: nearer points' elevations smear: a sensor's beams leave it off its axis (BALM's OS0 splits
# its rings in two within about 3 m)
_MIN_RANGE = 4.0
_MIN_RING_POINTS = 3  # fewer points between two gaps are strays (a mixed pixel), not a ring
# Two neighbouring clusters are rings when each is narrower than the gap between their centres; a
# scan has rings when at least this many such pairs hold this share of its points. BALM's OS0: 24-59
# pairs, 20-98 % (its rings smeared to 0.5-1.1 deg where the sensor turned during a sweep); Kurt3D's
# tilting scanner: at most 13 pairs, 10 %; the OctoMap scan none; the mine sim's 16 rings 15, 98 %.
_MIN_RING_PAIRS = 8
_MIN_RING_SHARE = 0.15


@njit(cache=True)
def ring_spacing(points):
    """The angle (rad) between neighbouring rings of a spinning lidar: the median gap between the
    clusters of the elevations of a scan's (n, 3) points in the sensor's frame (x forward, z up);
    0 when they show no rings."""
    n = points.shape[0]
    stride = max(1, n // _SAMPLE)
    bins = int(np.ceil(np.pi / _BIN)) + 1
    counts = np.zeros(bins, dtype=np.int64)
    sampled = 0
    for i in range(0, n, stride):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        rho = np.sqrt(x * x + y * y)
        if rho * rho + z * z >= _MIN_RANGE * _MIN_RANGE:
            counts[int((np.arctan2(z, rho) + 0.5 * np.pi) / _BIN)] += 1
            sampled += 1
    # clusters: occupied bins with gaps narrower than _RING_GAP between them; (centre, width, points)
    gap_bins = int(np.ceil(_RING_GAP / _BIN))
    centre, width, held = np.empty(bins), np.empty(bins), np.empty(bins, dtype=np.int64)
    n_clusters, b = 0, 0
    while b < bins:
        if counts[b] == 0:
            b += 1
            continue
        first, last, total, moment, empty = b, b, 0, 0.0, 0
        while b < bins and empty < gap_bins:
            if counts[b] > 0:
                last, empty = b, 0
                total += counts[b]
                moment += counts[b] * (b + 0.5)
            else:
                empty += 1
            b += 1
        if total >= _MIN_RING_POINTS:
            centre[n_clusters], width[n_clusters], held[n_clusters] = moment / total, last + 1 - first, total
            n_clusters += 1
    gaps = np.empty(max(n_clusters - 1, 0))
    n_pairs, in_pairs = 0, 0
    for c in range(n_clusters - 1):
        gap = centre[c + 1] - centre[c]
        if width[c] < gap and width[c + 1] < gap:
            gaps[n_pairs] = gap
            n_pairs += 1
            in_pairs += held[c]
    if n_pairs < _MIN_RING_PAIRS or in_pairs < _MIN_RING_SHARE * sampled:
        return 0.0
    return median(gaps[:n_pairs]) * _BIN


@njit(cache=True)
def with_footprint(sums, origin, spacing):
    """Voxel sums (m, 10: n, sum x, upper triangle of sum x x^T, about some point) plus, per voxel,
    n (r dphi)^2 / 12 e e^T: e the elevation direction at the voxel's mean, r its range from the
    sensor at `origin` (in the sums' frame), dphi the rings' `spacing` (rad)."""
    out = sums.copy()
    if spacing == 0.0:
        return out
    for v in range(sums.shape[0]):
        n = sums[v, 0]
        x, y, z = sums[v, 1] / n - origin[0], sums[v, 2] / n - origin[1], sums[v, 3] / n - origin[2]
        rho = np.sqrt(x * x + y * y)
        r = np.sqrt(rho * rho + z * z)
        if rho == 0.0:
            continue  # straight up or down: no elevation direction (and no ring reaches it)
        f = n * (r * spacing) ** 2 / 12.0
        ex, ey, ez = -x * z / (rho * r), -y * z / (rho * r), rho / r
        out[v, 4] += f * ex * ex
        out[v, 5] += f * ex * ey
        out[v, 6] += f * ex * ez
        out[v, 7] += f * ey * ey
        out[v, 8] += f * ey * ez
        out[v, 9] += f * ez * ez
    return out
