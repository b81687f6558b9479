"""Occupancy at arbitrary points: the probability of the cell of size R centred on each point.

Points whose cells lie on one common lattice (for instance the centres of a grid) are evaluated
together, one small grid per block of BLOCK cells along each axis, so a dense set of points costs
about as much as the grid they sample. Other points get a grid of one cell each, and
cost a few milliseconds each: a request may need at most MAX_GRIDS grids. Monte Carlo, as
every query of the fleet map, until the analytic evaluation is wired in.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import map_estimate

BLOCK = 64  # cells per axis of one evaluation grid
SNAP = 1e-6  # points within SNAP * R of a common lattice share it
MAX_GRIDS = 1000  # evaluation grids per request: about 5 ms each on the Intel map


def plan(xy: np.ndarray, resolution: float) -> list[tuple[Grid, np.ndarray, np.ndarray]]:
    """The grids that hold the cell [p - R/2, p + R/2) of every point p of `xy` (n, d):
    (grid, indices of its points, their cells as array indices), cheap to compute."""
    scaled = (xy - resolution / 2) / resolution  # min corner of each point's cell, in cells
    index = np.floor(scaled)
    offset = np.round((scaled - index) / SNAP).astype(np.int64)  # where in its lattice cell
    index = index.astype(np.int64)
    wrap = offset >= round(1 / SNAP)  # an offset that rounds up to 1 is offset 0 of the next cell
    index[wrap] += 1
    offset[wrap] = 0

    groups: dict[tuple, list[int]] = defaultdict(list)
    for i, key in enumerate(zip(map(tuple, offset), map(tuple, index // BLOCK))):
        groups[key].append(i)
    out = []
    for members in groups.values():
        members = np.array(members)
        idx = index[members]
        first = idx.min(axis=0)
        origin = (first + offset[members[0]] * SNAP) * resolution
        grid = Grid(origin, resolution, tuple(idx.max(axis=0) - first + 1))
        out.append((grid, members, tuple((idx - first)[:, ::-1].T)))  # arrays are [iy, ix] / [iz, iy, ix]
    return out


def point_probabilities(
    fleet_map, xy: np.ndarray, resolution: float, robots: Sequence[str] | None = None, grids: list | None = None
) -> np.ndarray:
    """float32 (n,) p(occupied) of the cell of size `resolution` centred on each point of `xy` (n, d);
    `grids` is plan(xy, resolution) when already made."""
    out = np.empty(len(xy), dtype=np.float32)
    for grid, members, cells in grids if grids is not None else plan(xy, resolution):
        out[members] = map_estimate(*fleet_map.counts(grid, robots), fleet_map.prior)[cells]
    return out
