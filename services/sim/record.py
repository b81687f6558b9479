"""What one `gmmap sim` run observed (the RunRecord, with the configuration it ran), its map
snapshots, and the graded box. services.sim.run fills a RunRecord; services.sim.grading reads it."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gmm_core import Grid
from services.api.params import MAX_CELLS
from services.config import GmmapConfig
from services.sim.config import SimConfig
from services.sim.fleet import SimulatedFleet
from services.sim.tap import WireEvent

RESOLUTION = 0.1  # m, of the maps graded against ground truth
MARGIN_3D = (8.0, 8.0, 3.0)  # m around the paths: the graded box of a 3D world


@dataclass
class Snapshot:
    t: float  # epoch seconds when it was asked for
    stored: dict[str, int]  # scans acknowledged per robot by then
    path: Path  # the npy file


@dataclass
class RunRecord:
    """Everything observed during one run; services.sim.grading turns it into numbers, services.sim.render
    into report.md and plots."""

    config: GmmapConfig  # what the run was asked to do: its `sim` section, the robots' fit, the server's
    fleet: SimulatedFleet
    grid: Grid
    update_every: int
    started: float  # epoch seconds when the agents were started
    wall_s: float = 0.0
    events: list[WireEvent] = field(default_factory=list)
    link_bytes: dict[str, tuple[int, int]] = field(default_factory=dict)  # robot -> (up, down)
    snapshots: list[Snapshot] = field(default_factory=list)
    # (epoch s asked, s to answer, X-Map-Age s) of each tile answered
    tile_latencies: list[tuple[float, float, float]] = field(default_factory=list)
    tile_errors: dict[str, int] = field(default_factory=dict)  # failed requests by kind
    published: dict[str, int] = field(default_factory=dict)  # scans each agent fitted and sent
    stored: dict[tuple[str, int], bytes] = field(default_factory=dict)  # the server's store
    components: dict[str, int] = field(default_factory=dict)
    agent_exit: dict[str, int] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    host_cpu: dict[str, float] | None = None  # services.host.cpu_shares over the drive, and loop_rate before it
    server_rss: list[tuple[float, int]] = field(default_factory=list)  # (epoch s, resident bytes) while it ran
    restart_s: float | None = None  # from a restart on the run's data directory to serving every node

    @property
    def options(self) -> SimConfig:
        return self.config.sim


def evaluation_grid(fleet: SimulatedFleet) -> Grid:
    """The graded box at RESOLUTION: a whole 2D world, or the paths of a 3D one plus MARGIN_3D."""
    raster = fleet.world.raster
    if fleet.world.dim == 2:
        return Grid.from_bbox(raster.origin, raster.upper, RESOLUTION)
    positions = np.concatenate([path[:, :3] for path in fleet.paths])
    lo = np.maximum(np.floor(positions.min(axis=0) - MARGIN_3D), raster.origin)
    hi = np.minimum(np.ceil(positions.max(axis=0) + MARGIN_3D), raster.upper)
    return Grid.from_bbox(lo, hi, RESOLUTION)


def blocks(grid: Grid, max_cells: int = MAX_CELLS) -> list[tuple[Grid, tuple[slice, ...]]]:
    """The grid cut into boxes of at most `max_cells`, each with its place in the grid's array.

    Near-cubic boxes: the longest side is cut first. A query traces only the components whose
    rays reach its box (gmm_core.scan_trace), so boxes cost about what the rays crossing them
    cost, where thin slabs of a 3D grid would each be crossed by nearly every ray.
    """
    shape = np.array(grid.shape)
    pieces = np.ones(grid.dim, dtype=np.int64)
    size = shape.copy()
    while np.prod(size) > max_cells and size.max() > 1:
        axis = int(np.argmax(size))
        pieces[axis] += 1
        size[axis] = -(-shape[axis] // pieces[axis])
    out = []
    for first in itertools.product(*(range(0, n, s) for n, s in zip(shape, size))):
        first = np.array(first)
        last = np.minimum(first + size, shape)
        box = Grid(grid.origin + first * grid.resolution, grid.resolution, tuple(int(v) for v in last - first))
        out.append((box, tuple(slice(int(a), int(b)) for a, b in zip(first[::-1], last[::-1]))))  # arrays: [iz, iy, ix]
    return out
