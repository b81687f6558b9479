"""Occupancy at arbitrary points: the probability of the cell of size R centred on each point.

Points whose cells lie on one common lattice (for instance the centres of a grid) are evaluated
together, one small grid per block of BLOCK cells along each axis, so a dense set of points costs
about as much as the grid they sample. Other points get a grid of one cell each, and
cost a few milliseconds each: a request may need at most MAX_GRIDS grids.

`method`: mc, those Monte-Carlo grids; analytic, the expected evidence of every component at
each point's cell (Eq. 3-10, gmm_core.analytic.cells), no grid and no sampling error, at a cost
per point; auto, analytic where that is cheaper: when one point costs less than
ANALYTIC_POINT_IN_GRIDS Monte-Carlo grids (measured by bench/points.py, docs/BENCHMARKS.md), so
few scattered points go analytic and cell centres of a lattice go Monte Carlo.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence

import numpy as np

from gmm_core import Grid
from gmm_core.analytic.cells import occupancy_at_cells
from gmm_core.occupancy import monte_carlo_estimate
from protocol.messages import POINT_METHODS

BLOCK = 64  # cells per axis of one evaluation grid
SNAP = 1e-6  # points within SNAP * R of a common lattice share it
MAX_GRIDS = 1000  # Monte-Carlo grids per request: about 5 ms each on the Intel map
MAX_ANALYTIC_POINTS = 1000  # points per request evaluated analytically: 6-15 ms each on the bench maps
METHODS = POINT_METHODS  # auto, analytic, mc: the HTTP API's and the Zenoh point query's
# One point analytically costs about this many one-cell Monte-Carlo grids: bench/points.py, 100
# scattered points, the mean of two runs (2D Intel 0.77, 0.66; 3D mine sim 0.57, 0.56)
ANALYTIC_POINT_IN_GRIDS = {2: 0.7, 3: 0.57}


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


def choose_method(n_points: int, n_grids: int, dim: int) -> str:
    """auto's choice: analytic when it costs less than the Monte-Carlo grids the points need."""
    return "analytic" if n_points * ANALYTIC_POINT_IN_GRIDS[dim] < n_grids else "mc"


def evaluate(
    fleet_map, xy: np.ndarray, resolution: float, robots: Sequence[str] | None = None, method: str = "auto"
) -> tuple[np.ndarray, str]:
    """point_probabilities of one request, and the method that evaluated them (auto's choice made);
    ValueError, saying why, for a request beyond one request's cost (MAX_ANALYTIC_POINTS, MAX_GRIDS).
    What `/v1/occupancy/points` and the Zenoh point query both answer; an unknown method is
    point_probabilities' ValueError."""
    grids = plan(xy, resolution)
    if method == "auto":
        method = choose_method(len(xy), len(grids), xy.shape[1])
    if method == "analytic" and len(xy) > MAX_ANALYTIC_POINTS:
        raise ValueError(f"at most {MAX_ANALYTIC_POINTS:,} points per request with method analytic")
    if method == "mc" and len(grids) > MAX_GRIDS:
        raise ValueError(
            f"the points need {len(grids)} separate evaluations, at most {MAX_GRIDS:,} per request: "
            f"scattered points cost one each, points on a common lattice of spacing `resolution` (such as "
            f"cell centres) share one per {BLOCK}x{BLOCK} cells"
        )
    return point_probabilities(fleet_map, xy, resolution, robots, grids, method), method


def point_probabilities(
    fleet_map,
    xy: np.ndarray,
    resolution: float,
    robots: Sequence[str] | None = None,
    grids: list | None = None,
    method: str = "mc",
) -> np.ndarray:
    """float32 (n,) p(occupied) of the cell of size `resolution` centred on each point of `xy` (n, d);
    `grids` is plan(xy, resolution) when already made; `method` one of METHODS."""
    if method not in METHODS:
        raise ValueError(f"method: must be one of {', '.join(METHODS)}, got {method!r}")
    if method != "mc":
        grids = grids if grids is not None else plan(xy, resolution)
        if method == "analytic" or choose_method(len(xy), len(grids), xy.shape[1]) == "analytic":
            return analytic_probabilities(fleet_map, xy, resolution, robots)
    out = np.empty(len(xy), dtype=np.float32)
    for grid, members, cells in grids if grids is not None else plan(xy, resolution):
        hits, misses = fleet_map.counts(grid, robots)
        out[members] = monte_carlo_estimate(hits, misses, fleet_map.samples_per_cell, fleet_map.prior)[cells]
    return out


def analytic_probabilities(fleet_map, xy: np.ndarray, resolution: float, robots: Sequence[str] | None) -> np.ndarray:
    """p(occupied) of each point's cell from the analytic evidence of the nodes that reach the
    points' box (gmm_core.analytic.cells: components whose cone misses a cell are skipped there).
    On the calling thread alone: the API's request threads may evaluate at the same time."""
    box = Grid.from_bbox(xy.min(axis=0) - resolution / 2, xy.max(axis=0) + resolution / 2, resolution)
    nodes = fleet_map.posed_components(box, robots)
    return occupancy_at_cells(nodes, xy, resolution, fleet_map.prior, parallel=False).astype(np.float32)
