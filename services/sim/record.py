"""What one `gmmap sim` run is asked to do and what it observed: the options, the map snapshots, the
RunRecord, and the graded box. services.sim.run fills a RunRecord; services.sim.grading reads it."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gmm_core import Grid
from services.api.params import MAX_CELLS
from services.sim.fleet import SimulatedFleet
from services.sim.tap import WireEvent

RESOLUTION = 0.1  # m, of the maps graded against ground truth
MARGIN_3D = (8.0, 8.0, 3.0)  # m around the paths: the graded box of a 3D world


@dataclass
class SimOptions:
    robots: int = 3
    world: str = "office"
    duration: float = 60.0  # simulated seconds per robot (= wall seconds: agents publish at `rate`)
    rate: float = 5.0
    seed: int = 0
    http_clients: int = 0
    report: str | None = None
    component_size: float | None = None  # m, passed to the agents' fit; None: their default
    fleet: str = "default"
    config: dict = field(default_factory=dict)  # the resolved configuration, copied into the report as is

    @property
    def scans(self) -> int:
        return max(1, math.ceil(self.duration * self.rate))


@dataclass
class Snapshot:
    t: float  # epoch seconds when it was asked for
    stored: dict[str, int]  # scans acknowledged per robot by then
    path: Path  # the npy file


@dataclass
class RunRecord:
    """Everything observed during one run; services.sim.grading turns it into numbers, services.sim.render
    into report.md and plots."""

    options: SimOptions
    fleet: SimulatedFleet
    grid: Grid
    update_every: int
    started: float  # epoch seconds when the agents were started
    wall_s: float = 0.0
    events: list[WireEvent] = field(default_factory=list)
    link_bytes: dict[str, tuple[int, int]] = field(default_factory=dict)  # robot -> (up, down)
    snapshots: list[Snapshot] = field(default_factory=list)
    tile_latencies: list[float] = field(default_factory=list)
    tile_errors: dict[str, int] = field(default_factory=dict)  # failed requests by kind
    published: dict[str, int] = field(default_factory=dict)  # scans each agent fitted and sent
    stored: dict[tuple[str, int], bytes] = field(default_factory=dict)  # the server's store
    components: dict[str, int] = field(default_factory=dict)
    agent_exit: dict[str, int] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    server_rss: list[tuple[float, int]] = field(default_factory=list)  # (epoch s, resident bytes) while it ran


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
