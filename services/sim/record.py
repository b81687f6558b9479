"""What one `gmmap sim` run observed (the RunRecord, with the configuration it ran), its map
snapshots, and the graded box. services.sim.run fills a RunRecord; services.sim.grading reads it."""

from __future__ import annotations

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


def slabs(grid: Grid, max_cells: int = MAX_CELLS) -> list[Grid]:
    """The grid cut along its first array axis (y in 2D, z in 3D) into pieces of at most `max_cells`."""
    per_slab = max(1, max_cells // (grid.n_cells // grid.array_shape[0]))
    pieces = []
    for first in range(0, grid.array_shape[0], per_slab):
        origin, shape = grid.origin.copy(), list(grid.shape)
        origin[-1] += first * grid.resolution
        shape[-1] = min(per_slab, grid.array_shape[0] - first)
        pieces.append(Grid(origin, grid.resolution, tuple(shape)))
    return pieces
