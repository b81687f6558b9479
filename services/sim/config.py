"""The `sim` section of the configuration: one simulated fleet (`gmmap sim`); the robots' fit is
the `fit` section and the server's reconstruction the `reconstruction` section."""

from __future__ import annotations

import math
from dataclasses import dataclass

from gmm_core.validation import require_count, require_number
from protocol import check_id
from services.sim.world_names import WORLD_NAMES


@dataclass(frozen=True)
class SimConfig:
    robots: int = 3  # robots in the fleet, >= 1
    world: str = "office"  # office, warehouse: 2D laser; mine: 3D lidar (services.sim.worlds)
    duration: float = 60.0  # simulated s each robot drives and publishes (wall: duration / time_scale)
    rate: float = 5.0  # scans per second per robot, > 0
    time_scale: float = 1.0  # simulated seconds per wall second, > 0: robots publish at rate x time_scale
    seed: int = 0  # world, paths, odometry and sensor noise
    http_clients: int = 0  # concurrent HTTP clients fetching map tiles meanwhile
    report: str | None = None  # a folder for report.json, report.md and the plots; None: none
    fleet: str = "default"
    http_token: str | None = None  # a file holding the bearer token that the sim's (or demo's) HTTP clients send
    http_ca: str | None = None  # PEM CA bundle that signed the server's TLS certificate; None: the system's

    def __post_init__(self):
        require_count("sim.robots", self.robots)
        require_number("sim.duration", self.duration, positive=True)
        require_number("sim.rate", self.rate, positive=True)
        require_number("sim.time_scale", self.time_scale, positive=True)
        require_count("sim.seed", self.seed, minimum=0)
        require_count("sim.http_clients", self.http_clients, minimum=0)
        check_id(self.fleet, "sim.fleet")
        if self.world not in WORLD_NAMES:
            raise ValueError(f"sim.world: must be one of {', '.join(WORLD_NAMES)}, got {self.world!r}")

    @property
    def wall_duration(self) -> float:
        """Wall seconds the robots publish for: the simulated duration over the time scale."""
        return self.duration / self.time_scale

    @property
    def wall_rate(self) -> float:
        """Scans per wall second per robot."""
        return self.rate * self.time_scale

    @property
    def scans(self) -> int:
        return max(1, math.ceil(self.duration * self.rate))
