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
than their spacing, read in each quadrant of azimuth apart (a sensor that turns during its sweep
shifts them from one side to the other), the spacing the median gap between neighbouring ones;
scans from sensors without rings (a tilting 2D scanner, a depth camera, a lidar tilted in the
scan's frame) show none and get no footprint.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from gmm_core.selection import median

_BIN = np.radians(0.02)  # elevation histogram bins: narrower than a ring's spread (0.2-0.3 deg at BALM)
_RING_GAP = np.radians(0.2)  # a gap at least this wide between elevations separates two rings
_SAMPLE = 16384  # points whose elevation is read: about 60 a ring in each quadrant for 64 rings
# m: nearer points' elevations smear: a sensor's beams leave it off its axis (BALM's OS0 splits
# its rings in two within about 3 m)
_MIN_RANGE = 4.0
_MIN_RING_POINTS = 3  # fewer points between two gaps are strays (a mixed pixel), not a ring
# Two neighbouring clusters are rings when each is narrower than the gap between their centres; a
# set of elevations has rings when at least this many such pairs hold this share of its points.
_MIN_RING_PAIRS = 8
_MIN_RING_SHARE = 0.15
# The four quadrants of azimuth are read apart first: a sensor that turns or tilts during its sweep
# shifts its rings' elevations from one side of the scan to the other, and over the whole sweep they
# smear into each other (BALM's OS0: #8 shows 23 pairs holding 16 % of its points, against 15 %
# needed; stretched 3x, so that its nearest points count, none), while within a quadrant they stay
# sharp (the quadrants read: 50 of 50 over BALM's 15 scans, 58 of 60 stretched 3x). A quadrant is read
# where it holds at least this many sampled points: sparser elevations scatter into clusters that
# pass for rings (evenly spread elevations do from a few hundred to about 1,000 points, never from
# 2,000). A scan has rings when at least two quadrants read do, three quarters of those read; else
# when its whole sweep does. Kurt3D's tilting scanner (most points within 4 m): one quadrant read, at
# most 8 pairs holding 3 % (another of 420-470 points shows 37-47 pairs holding half of them: not
# read); the OctoMap scan: two read, no pairs; the mine sim's 16 rings: all read.
_MIN_QUADRANT_POINTS = 2048


@njit(cache=True)
def ring_spacing(points):
    """The angle (rad) between neighbouring rings of a spinning lidar: the median of the spacings of
    the azimuth quadrants whose elevations show rings where enough do, else the spacing of the whole
    sweep's elevations (_elevation_spacing); 0 when they show no rings. `points` (n, 3) in the
    sensor's frame (x forward, z up)."""
    n = points.shape[0]
    stride = max(1, n // _SAMPLE)
    bins = int(np.ceil(np.pi / _BIN)) + 1
    counts = np.zeros((4, bins), dtype=np.int64)
    sampled = np.zeros(4, dtype=np.int64)
    for i in range(0, n, stride):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        rho = np.sqrt(x * x + y * y)
        if rho * rho + z * z >= _MIN_RANGE * _MIN_RANGE:
            quadrant = 2 * (x < 0.0) + (y < 0.0)
            counts[quadrant, int((np.arctan2(z, rho) + 0.5 * np.pi) / _BIN)] += 1
            sampled[quadrant] += 1
    spacings = np.empty(4)
    n_read, n_rings = 0, 0
    for quadrant in range(4):
        if sampled[quadrant] >= _MIN_QUADRANT_POINTS:
            n_read += 1
            spacing = _elevation_spacing(counts[quadrant], sampled[quadrant])
            if spacing > 0.0:
                spacings[n_rings] = spacing
                n_rings += 1
    if n_rings >= 2 and 4 * n_rings >= 3 * n_read:
        return median(spacings[:n_rings])
    return _elevation_spacing(counts.sum(axis=0), sampled.sum())


@njit(cache=True)
def _elevation_spacing(counts, sampled):
    """The median gap (rad) between the clusters of elevations (`counts` per _BIN of `sampled` points)
    that are rings, or 0 where too few pairs of clusters are."""
    bins = counts.shape[0]
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
